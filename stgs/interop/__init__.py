"""Interchange with the 3DGS ecosystem: the INRIA PLY, SPZ and glTF KHR_gaussian_splatting, in and out.

`files` reads and writes any of them by name (`Splats`, stgs.interop.splats); `frames` gives the Gaussians of
one frame of a model dir or packaged tree; `static` makes a static layer of a file trained elsewhere
(docs/INTEROP.md).
"""
