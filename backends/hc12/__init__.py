"""HC-12 433 MHz radio backend: relay or re-transmit Aurora frames within the air link's
budget, and provision the module safely (``aurora-gateway hc12 …``).  See README.md."""
