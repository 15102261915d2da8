"""The gateway's I/O: one loop thread (:mod:`~gateway.io.ioloop`), ports and listeners on it
(:mod:`~gateway.io.port`), the ports themselves (:mod:`~gateway.io.transport`), the links of a
flight-side backend (:mod:`~gateway.io.links`) and the reconnect policy
(:mod:`~gateway.io.backoff`)."""
