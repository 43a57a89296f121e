"""stgs.server: the async HTTP service for packaged scenes (`stgs serve`, issue 4)."""
