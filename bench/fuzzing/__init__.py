"""The parsers under fuzzed input: cases per second and findings."""
