"""What runs the layers: the pump that feeds a source's samples to the core and its events to sinks,
the daemon, replay."""
