"""`stgs prepare`'s choices and defaults, in a module light enough for the command line's parser (no numpy,
OpenCV or PyAV)."""

LAYOUTS = ("frames", "videos")
"""frames: frameNNNNNN/images/<cam>.png; videos: videos/<cam>.mkv (FFV1, lossless RGB)."""
SYNC_METHODS = ("auto", "audio", "index")
CAMERA_MODELS = ("SIMPLE_RADIAL", "SIMPLE_PINHOLE", "RADIAL", "PINHOLE", "OPENCV", "FULL_OPENCV", "OPENCV_FISHEYE")
"""Lens models COLMAP may fit (undistorted afterwards by stgs.data.distortion)."""
DEFAULT_CAMERA_MODEL = "SIMPLE_RADIAL"
"""One focal length (square pixels) and one radial term: the models with separate fx and fy let bundle
adjustment trade the focal lengths against the poses on a rig's few views (docs/BENCHMARKS.md, "Captures")."""
RIG_RADIUS = 3.2
"""Mean distance of the prepared cameras' centres from their centroid: a rig the trainer takes at its own unit
(stgs.data.units: the synthetic orbit's radius)."""
DEFAULT_CALIB_FRAMES = 1
"""Frames the rig is calibrated on (docs/BENCHMARKS.md, "Captures": calibration time and camera error against
the count)."""
