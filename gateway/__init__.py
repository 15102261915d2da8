"""Aurora Gateway: takes the Aurora flight computer's telemetry in and fans it out to the
protocols ground tools already speak."""

__version__ = "0.1.0"
