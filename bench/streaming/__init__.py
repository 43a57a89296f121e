"""Streaming over networks: the simulator against emulation, and every ABR rule over trace sets."""
