"""The deformation's arithmetic, by name (light: the command line lists them before torch loads)."""

PRECISIONS = ("fp32", "bf16", "int16")
"""Arithmetic of the native deformation: float32; bf16 inputs/weights with float32 accumulation; int16
inputs/weights (one scale per input row and per weight column) with exact int32 sums."""
