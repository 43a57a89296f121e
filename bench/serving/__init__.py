"""The server: throughput and latency against nginx, CPU per request, and the soak beside hostile clients."""
