"""MAVLink: the rocket as a vehicle QGroundControl, MAVProxy and MAVSDK understand, a
mavlink-router-style router between endpoints, MAVLink 2 signing, and MAVLink vehicles as a
source.  See ``backends/mavlink/README.md``."""
