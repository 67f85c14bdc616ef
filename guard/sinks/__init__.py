"""Sinks: listen to the core's events (STATUSTEXT, MCAP log, replay report, figures)."""
