"""A camera's calibration as captures give it (COLMAP's models, nerfstudio's parameters), and the undistortion that
turns its frames into the pinhole views the trainer reads.

Distorted frames are undistorted to the same size and the same pinhole intrinsics (fx, fy, cx, cy): pixels that
no source pixel reaches are black. OpenCV does the remapping (bilinear); the fisheye model through cv2.fisheye.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np
import torch

PINHOLE_MODELS = ("SIMPLE_PINHOLE", "PINHOLE")
MODELS = (*PINHOLE_MODELS, "SIMPLE_RADIAL", "RADIAL", "OPENCV", "FULL_OPENCV", "OPENCV_FISHEYE")
"""The camera models captures may use (COLMAP's names); the distorted ones are undistorted once into a cache."""
_COEFFICIENTS = {"SIMPLE_PINHOLE": 0, "PINHOLE": 0, "SIMPLE_RADIAL": 4, "RADIAL": 4, "OPENCV": 4, "FULL_OPENCV": 8,
                 "OPENCV_FISHEYE": 4}
"""Length of Intrinsics.coefficients per model (OpenCV's order; the radial models' unused terms zero)."""
_GIVEN = {"SIMPLE_RADIAL": 1, "RADIAL": 2}
"""Coefficients a radial model carries: the rest of its stored ones are zero."""


@dataclass
class Intrinsics:
    """One camera's intrinsics and lens distortion."""

    model: str
    """COLMAP's name of the camera model (MODELS)."""
    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    coefficients: tuple[float, ...] = ()
    """OpenCV's distortion coefficients: (k1, k2, p1, p2[, k3, k4, k5, k6]), or (k1, k2, k3, k4) for the fisheye
    model; empty for a pinhole camera."""
    _maps: tuple[np.ndarray, np.ndarray] | None = field(default=None, repr=False, compare=False)

    @classmethod
    def from_colmap(cls, model: str, width: int, height: int, params: list[float]) -> Intrinsics:
        """From COLMAP's parameter list of `model` (ValueError for an unsupported model or bad values)."""
        p = [float(v) for v in params]
        if not np.isfinite(p).all():
            raise ValueError(f"{model} parameters must be finite")
        if model == "SIMPLE_PINHOLE":
            out = cls(model, width, height, p[0], p[0], p[1], p[2])
        elif model == "PINHOLE":
            out = cls(model, width, height, p[0], p[1], p[2], p[3])
        elif model == "SIMPLE_RADIAL":
            out = cls(model, width, height, p[0], p[0], p[1], p[2], (p[3], 0.0, 0.0, 0.0))
        elif model == "RADIAL":
            out = cls(model, width, height, p[0], p[0], p[1], p[2], (p[3], p[4], 0.0, 0.0))
        elif model in ("OPENCV", "FULL_OPENCV", "OPENCV_FISHEYE"):
            out = cls(model, width, height, p[0], p[1], p[2], p[3], tuple(p[4:]))
        else:
            raise ValueError(f"the {model} model is not supported (supported: {', '.join(MODELS)})")
        if not (out.fx > 0 and out.fy > 0):
            raise ValueError(f"focal lengths must be positive (fx {out.fx}, fy {out.fy})")
        return out

    @property
    def distorted(self) -> bool:
        return any(c != 0 for c in self.coefficients)

    @property
    def fisheye(self) -> bool:
        return self.model == "OPENCV_FISHEYE"

    def matrix(self) -> torch.Tensor:
        """(3, 3) float64 pinhole intrinsics of the (undistorted) views."""
        return torch.tensor([[self.fx, 0, self.cx], [0, self.fy, self.cy], [0, 0, 1]], dtype=torch.float64)

    def to_json(self) -> dict:
        return {"model": self.model, "width": self.width, "height": self.height, "fx": self.fx, "fy": self.fy,
                "cx": self.cx, "cy": self.cy, "coefficients": list(self.coefficients)}

    @classmethod
    def from_json(cls, d: dict) -> Intrinsics:
        """The inverse of to_json, checked as from_colmap checks (ValueError naming the field at fault). A
        radial model's coefficients may be given without their trailing zeros."""
        if not isinstance(d, dict):
            raise ValueError("a lens must be an object with model, width, height, fx, fy, cx, cy, coefficients")
        try:
            model, width, height = str(d["model"]), int(d["width"]), int(d["height"])
            fx, fy, cx, cy = (float(d[k]) for k in ("fx", "fy", "cx", "cy"))
            coefficients = [float(c) for c in d.get("coefficients", [])]
        except KeyError as exc:
            raise ValueError(f"a lens needs the field {exc.args[0]!r}") from None
        except (TypeError, ValueError):
            raise ValueError("a lens's width and height must be integers, its fx, fy, cx, cy and coefficients "
                             "numbers") from None
        if model not in MODELS:
            raise ValueError(f"the {model} model is not supported (supported: {', '.join(MODELS)})")
        if not (width > 0 and height > 0):
            raise ValueError(f"a lens's width and height must be positive, not {width}x{height}")
        stored, given = _COEFFICIENTS[model], _GIVEN.get(model, _COEFFICIENTS[model])
        if len(coefficients) not in (0, given, stored) or any(coefficients[given:]):
            raise ValueError(f"the {model} model takes {given} coefficients, not {coefficients}")
        if (model.startswith("SIMPLE_") or model == "RADIAL") and fx != fy:
            raise ValueError(f"the {model} model has one focal length: fx {fx} and fy {fy} differ")
        out = cls(model, width, height, fx, fy, cx, cy, tuple(coefficients + [0.0] * (stored - len(coefficients))))
        return cls.from_colmap(model, width, height, out.colmap_params())

    @classmethod
    def pinhole_of(cls, camera) -> Intrinsics:
        """The PINHOLE lens of a stgs.camera.Camera (its K at its size)."""
        K = camera.K
        return cls.from_colmap("PINHOLE", camera.width, camera.height,
                               [float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])])

    def colmap_params(self) -> list[float]:
        """COLMAP's parameter list for this model (the inverse of from_colmap)."""
        k = list(self.coefficients)
        if self.model == "SIMPLE_PINHOLE":
            return [self.fx, self.cx, self.cy]
        if self.model == "SIMPLE_RADIAL":
            return [self.fx, self.cx, self.cy, k[0]]
        if self.model == "RADIAL":
            return [self.fx, self.cx, self.cy, k[0], k[1]]
        return [self.fx, self.fy, self.cx, self.cy, *k]

    def resized(self, width: int, height: int) -> Intrinsics:
        """The same lens on frames scaled to width x height (the same aspect; ValueError otherwise)."""
        sx, sy = width / self.width, height / self.height
        if abs(sx / sy - 1) > 2e-3:
            raise ValueError(f"a lens calibrated at {self.width}x{self.height} does not fit {width}x{height} "
                             "frames (another aspect ratio)")
        return Intrinsics(self.model, width, height, self.fx * sx, self.fy * sy, self.cx * sx, self.cy * sy,
                          self.coefficients)

    def undistort(self, rgb: np.ndarray, nearest: bool = False) -> np.ndarray:
        """(H, W, 3) uint8 view (or (H, W) mask, `nearest`: no new values) undistorted to the pinhole intrinsics
        (matrix()) at the same size (unchanged where the camera has no distortion)."""
        if not self.distorted:
            return rgb
        if rgb.shape[:2] != (self.height, self.width):
            raise ValueError(f"frame is {rgb.shape[1]}x{rgb.shape[0]}, the camera {self.width}x{self.height}")
        if self._maps is None:
            K, size = self.matrix().numpy(), (self.width, self.height)
            D = np.array(self.coefficients, dtype=np.float64)
            if self.fisheye:
                self._maps = cv2.fisheye.initUndistortRectifyMap(K, D, np.eye(3), K, size, cv2.CV_32FC1)
            else:
                self._maps = cv2.initUndistortRectifyMap(K, D, None, K, size, cv2.CV_32FC1)
        map_x, map_y = self._maps
        return cv2.remap(rgb, map_x, map_y, cv2.INTER_NEAREST if nearest else cv2.INTER_LINEAR,
                         borderMode=cv2.BORDER_CONSTANT)

    def distort(self, rgb: np.ndarray) -> np.ndarray:
        """The inverse: a pinhole view (intrinsics matrix()) as this camera's lens records it (tests and synthetic
        captures)."""
        if not self.distorted:
            return rgb
        K = self.matrix().numpy()
        D = np.array(self.coefficients, dtype=np.float64)
        ys, xs = np.mgrid[0:self.height, 0:self.width].astype(np.float64)
        pixels = np.stack([xs.ravel(), ys.ravel()], 1)[:, None]
        if self.fisheye:
            pinhole = cv2.fisheye.undistortPoints(pixels, K, D, P=K)
        else:
            pinhole = cv2.undistortPoints(pixels, K, D, P=K,
                                          criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-10))
        maps = pinhole.reshape(self.height, self.width, 2).astype(np.float32)
        return cv2.remap(rgb, maps[..., 0], maps[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
