"""Zenoh backend and source: every update published on Zenoh, and gateways fed from Zenoh.

See README.md in this directory for the key layout, the payloads, the configuration keys and
the fleet set-up.
"""
