"""Backends: each speaks one protocol to the outside world.  See :mod:`gateway.backend` for
what a backend must and might implement; they are found by name through the
``aurora_gateway.backends`` entry-point group."""
