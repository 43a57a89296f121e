"""stgs.harness: the throughput simulation harness (`stgs sim`)."""
