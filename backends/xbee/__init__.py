"""XBee radio link (seed 004): API frames (frames.py) and compact link packets (packets.py)."""
