"""What flows between the layers: samples (sources to core), events (core to sinks), sensor names."""
