"""UAVTalk (LibrePilot 16.09): object definitions, packet codec and telemetry sessions."""
