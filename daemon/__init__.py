"""The acquisition daemon (import name ``sssphase_daemon``): owns devices, serves them over ZeroMQ."""
