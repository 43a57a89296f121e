"""The web player in headless Chromium: frame time per stage, and Spark against our splat pass."""
