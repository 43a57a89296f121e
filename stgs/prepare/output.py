"""What `stgs prepare` writes: a calibrated capture in one of the readers' layouts (stgs.data.capture), its frames
undistorted to pinhole views, and the record that lets a killed run resume.

- `frames`: `frameNNNNNN/images/<cam>.png`, the model in `frame000000/sparse/0`;
- `videos`: `videos/<cam>.mkv` (FFV1, lossless RGB), the model in `sparse/0`.

Everything is written inside a staging folder beside the output (`.<name>.partial`), which is renamed into place
when the capture is whole. Each file is written under a temporary name and renamed, so a file that exists is
whole; `prepare_state.json` names the cameras that are done.
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable, Iterator
from pathlib import Path

import av
import numpy as np

from stgs.data.distortion import Intrinsics
from stgs.data.frames import write_png
from stgs.errors import StgsError
from stgs.fsio import atomic_write_bytes

STATE = "prepare_state.json"
REPORT = "prepare_report.json"


def staging_dir(out: Path) -> Path:
    return out.parent / f".{out.name}.partial"


def model_dir(root: Path, layout: str) -> Path:
    return root / "frame000000" / "sparse" / "0" if layout == "frames" else root / "sparse" / "0"


def image_name(camera: str, layout: str) -> str:
    """The name a camera's view has in the written model (what stgs.data.capture matches cameras by)."""
    return f"{camera}.png" if layout == "frames" else f"{camera}.mkv"


def write_json(path: Path, data: dict) -> None:
    atomic_write_bytes(path, (json.dumps(data, indent=1) + "\n").encode())


def read_state(root: Path) -> dict | None:
    path = root / STATE
    if not path.is_file():
        return None
    try:
        return json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise StgsError(f"{path}: unreadable ({exc}); remove {root} and start again") from None


def write_model(folder: Path, lenses: dict[str, Intrinsics], viewmats: dict[str, np.ndarray], layout: str,
                points: np.ndarray, colours: np.ndarray) -> None:
    """A binary COLMAP model (written by pycolmap) of the undistorted rig: one PINHOLE camera per view."""
    import pycolmap

    rec = pycolmap.Reconstruction()
    for i, (cam, lens) in enumerate(lenses.items(), 1):
        rec.add_camera_with_trivial_rig(pycolmap.Camera(camera_id=i, model="PINHOLE", width=lens.width,
                                                        height=lens.height,
                                                        params=[lens.fx, lens.fy, lens.cx, lens.cy]))
        view = viewmats[cam]
        pose = pycolmap.Rigid3d(pycolmap.Rotation3d(view[:3, :3]), view[:3, 3])
        rec.add_image_with_trivial_frame(pycolmap.Image(name=image_name(cam, layout), camera_id=i, image_id=i), pose)
    for xyz, rgb in zip(points, colours, strict=True):
        rec.add_point3D(np.asarray(xyz, dtype=np.float64), pycolmap.Track(), np.asarray(rgb, dtype=np.uint8))
    folder.mkdir(parents=True, exist_ok=True)
    rec.write_binary(str(folder))


def _in_order(camera: str, frames: Iterator[tuple[int, np.ndarray]], first: int, count: int,
              tick: Callable[[], None]) -> Iterator[tuple[int, np.ndarray]]:
    """The frames `first`..`first + count - 1` as (position in the span, RGB), `tick` called once each is
    handled; StgsError where the video skips a frame or ends early."""
    expected = first
    for index, rgb in frames:
        if index != expected:
            raise StgsError(f"camera {camera}: frame {expected} is missing from its video (got {index} next)")
        yield index - first, rgb
        tick()
        expected += 1
    if expected != first + count:
        raise StgsError(f"camera {camera}: its video ends at frame {expected}, before {first + count}")


def write_frames(root: Path, camera: str, frames: Iterator[tuple[int, np.ndarray]], first: int, count: int,
                 fix: Callable[[np.ndarray], np.ndarray], tick: Callable[[], None]) -> int:
    """The camera's frames `first`.. as `frameNNNNNN/images/<camera>.png` (N counted from the span's start),
    each through `fix`; frames already written (a resumed run) are skipped. Returns the bytes written."""
    written = 0
    for position, rgb in _in_order(camera, frames, first, count, tick):
        path = root / f"frame{position:06d}" / "images" / f"{camera}.png"
        if not path.is_file():
            write_png(path, fix(rgb))
        written += path.stat().st_size
    return written


def write_video(root: Path, camera: str, frames: Iterator[tuple[int, np.ndarray]], first: int, count: int,
                fix: Callable[[np.ndarray], np.ndarray], tick: Callable[[], None], rate) -> int:
    """The camera's frames as `videos/<camera>.mkv`, FFV1 lossless RGB, written under a temporary name and
    renamed. Returns its bytes."""
    path = root / "videos" / f"{camera}.mkv"
    if path.is_file():
        return path.stat().st_size
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.stem}.tmp.mkv")
    try:
        with av.open(str(tmp), "w") as container:
            stream = container.add_stream("ffv1", rate=rate)
            stream.pix_fmt = "bgr0"
            for position, rgb in _in_order(camera, frames, first, count, tick):
                view = fix(rgb)
                if position == 0:
                    stream.width, stream.height = view.shape[1], view.shape[0]
                container.mux(stream.encode(av.VideoFrame.from_ndarray(view, format="rgb24")))
            container.mux(stream.encode())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return path.stat().st_size
