"""XBee radio link (seed 004): API frames (:mod:`.frames`) and the link's compact packets
(:mod:`.packets`), both sans-I/O."""
