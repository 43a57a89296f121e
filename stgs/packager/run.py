"""`pack`: one pack run, in this process (stgs.packager.packer) or as tasks on a Ray cluster
(stgs.packager.tasks), which both build on the packer."""

from __future__ import annotations

from pathlib import Path

from stgs.packager.config import PackConfig
from stgs.packager.packer import Packer


def pack(model_dir: Path, out: Path, cfg: PackConfig | None = None, progress: bool = True, ray: str | None = None,
         retries: int = 3) -> dict:
    """Package a model dir into a DASH tree at `out`; returns the stats document. `ray`: None (this process, on
    a pool of `cfg.jobs` encoders) or a Ray address (stgs.tasks.open_runner; stgs.packager.tasks)."""
    packer = Packer(model_dir, Path(out), cfg or PackConfig(), progress)
    if ray is None:
        packer.prepare_output()
        return packer.run()
    from stgs.packager.tasks import run_tasks  # Ray's side loads only when asked for
    from stgs.tasks import open_runner

    runner = open_runner(ray, retries, progress)  # before anything is written: a bad address leaves no output
    try:
        packer.prepare_output()
        return run_tasks(packer, runner)
    finally:
        runner.close()
