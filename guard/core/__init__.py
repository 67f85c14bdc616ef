"""The core: pure, synchronous, no I/O. One step, sample in, events out (`guard.core.monitor.Monitor`)."""
