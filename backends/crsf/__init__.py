"""CRSF / ExpressLRS backend: the rocket's state, altitude, vertical speed, attitude and
health as telemetry sensors on an EdgeTX radio (see README.md in this directory)."""
