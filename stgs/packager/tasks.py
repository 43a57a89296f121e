"""`stgs pack --ray`: a pack as tasks on a Ray cluster, writing the same tree as a local pack.

Per GOP a prepare task sorts and tiles the GOP, writes its keyframe segment into the tree and saves the prepared
GOP (feature frames, ranges, reference views; safetensors) under `OUT/.pack-work/`; per GOP x ladder point an
encode task loads it, encodes one ladder point of one codec, writes the init and media segments and measures
them, with the same Packer code as a local pack. The driver records each finished task in the resume state as
it arrives (so `--resume` after the driver dies re-runs only what is missing), tells the manifest builder of
every segment, removes the work folder and writes stats.json and, last, the MPD. Task logs stay under
`OUT/.pack-logs/` (hidden: never served).
"""

from __future__ import annotations

import dataclasses
import shutil
from dataclasses import dataclass
from pathlib import Path

from stgs.codec.plas_config import PLASConfig
from stgs.codec.video import CODECS
from stgs.errors import StgsError
from stgs.packager.ladder import LadderRules
from stgs.packager.packer import PackConfig, Packer, point_task_name
from stgs.packager.segments import load_prepared, lossy_rungs, save_prepared
from stgs.tasks import Runner, Task
from stgs.tree import KEYFRAME_REP, PACK_LOGS, PACK_WORK, feature_path, keyframe_path


@dataclass(frozen=True)
class PackJob:
    """What a task needs to rebuild the pack where it runs (plain data)."""

    model_dir: str
    out: str
    cfg: dict


def _packer(job: PackJob) -> Packer:
    doc = job.cfg
    points = {name: tuple(doc[name]) if doc[name] is not None else None for name in ("qps", "av1_qps")}
    cfg = PackConfig(**{**doc, **points, "codecs": tuple(doc["codecs"]),
                        "keyframe_rungs": tuple(doc["keyframe_rungs"]), "rules": LadderRules(**doc["rules"]),
                        "plas": PLASConfig(**doc["plas"]), "resume": False})
    return Packer(Path(job.model_dir), Path(job.out), cfg, progress=False)


def prepared_path(out: Path, k: int) -> Path:
    return Path(out) / PACK_WORK / f"gop_{k:05d}.safetensors"


def prepare_task(job: PackJob, k: int) -> dict:
    packer = _packer(job)
    gop = packer.prepare_gop(k)
    packer.write_keyframes(gop)
    save_prepared(gop, prepared_path(packer.out, k))
    return {"keyframe_bytes": len(gop.keyframe)}


def _keyframe_reps(packer: Packer) -> list[str]:
    return [KEYFRAME_REP, *lossy_rungs(packer.cfg.lossy_keyframes())]


def encode_task(job: PackJob, k: int, codec: str, q: int) -> dict:
    packer = _packer(job)
    data = {rep: (packer.out / keyframe_path(packer.version_dir, k, rep)).read_bytes()
            for rep in _keyframe_reps(packer)}
    keyframe = data.pop(KEYFRAME_REP)
    gop = load_prepared(prepared_path(packer.out, k), keyframe, packer.meta, data)
    files, result = packer.encode_segment(gop, CODECS[codec], q)
    return {"rep": CODECS[codec].rep_id(q), "files": files, "result": result}


def run_tasks(packer: Packer, runner: Runner) -> dict:
    """The pack on `runner` (after Packer.prepare_output); returns the stats document."""
    cfg, out, state = packer.cfg, packer.out, packer.opened_state()
    job = PackJob(str(packer.model_dir.resolve()), str(out.resolve()), dataclasses.asdict(cfg))
    packer.write_static()
    tasks = []
    ladder = cfg.encodes()
    for k in range(packer.meta.num_gops):
        pending = [(c, q) for c, q in ladder if state.done(out, point_task_name(k, c, q)) is None]
        prepare = f"gop{k}-prepare"
        if pending or not all((out / keyframe_path(packer.version_dir, k, rep)).is_file()
                              for rep in _keyframe_reps(packer)):
            tasks.append(Task(prepare, prepare_task, (job, k)))
        tasks += [Task(point_task_name(k, c, q), encode_task, (job, k, c.name, q), after=(prepare,))
                  for c, q in pending]
    inits: dict[str, set[str]] = {}

    def on_result(name: str, result: dict) -> None:
        if "files" in result:
            state.record(name, result["files"], result["result"])
            rep = result["rep"]
            inits.setdefault(rep, set()).add(result["files"][feature_path(packer.version_dir, rep, None)])

    runner.run(tasks, out / PACK_LOGS, "pack GOPs x ladder points", on_result)
    for rep, digests in inits.items():
        if len(digests) > 1:
            raise StgsError(f"{rep}: the GOPs' encodes produced {len(digests)} different init segments; a "
                            "Representation needs one (are the workers running different ffmpeg builds?)")
    for k in range(packer.meta.num_gops):
        packer.report_keyframes(k, {rep: (out / keyframe_path(packer.version_dir, k, rep)).stat().st_size
                                    for rep in _keyframe_reps(packer)})
        for codec, q in ladder:
            done = state.done(out, point_task_name(k, codec, q))
            if done is None:
                raise StgsError(f"{out}: GOP {k} of {codec.rep_id(q)} is missing or changed after its task "
                                "finished")
            packer.builder.on_feature_segment(codec.rep_id(q), packer.segment_record(k, done))
    shutil.rmtree(out / PACK_WORK, ignore_errors=True)
    return packer.finish()
