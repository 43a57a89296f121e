"""The `stgs` command: one entry point, one subcommand per pipeline stage.

User mistakes (bad paths, bad configs, bad input files) raise the library's
StgsError, or UsageError here for a bad combination of flags, and end as one
`stgs: ...` line on stderr with exit status 2; a FieldError names a config
field, which FLAGS turns into the flag that sets it. Anything else is a bug
and keeps its traceback.
"""

from __future__ import annotations

import argparse
import dataclasses
import importlib
import math
import sys
from pathlib import Path

from stgs.errors import FieldError, StgsError


class UsageError(StgsError):
    """Flags that do not go together or do not parse (the CLI's own error)."""


FLAGS = {"qps": "--qps", "preset": "--preset", "codec": "--codec", "jobs": "--jobs", "abr": "--abr",
         "buffer_s": "--buffer", "start_s": "--start", "duration_s": "--duration", "precision": "--precision",
         "camera": "--camera", "eye": "--eye/--target", "holdout": "--holdout", "qp": "--qp", "speed": "--speed"}
"""Config field -> the flag that sets it, for FieldError messages."""


def _int_at_least(lowest: int, words: str):
    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"not an integer: {text!r}") from None
        if value < lowest:
            raise argparse.ArgumentTypeError(f"must be {words}: {value}")
        return value

    return parse


_positive_int = _int_at_least(1, "positive")
_non_negative_int = _int_at_least(0, "0 or more")


def _names(text: str) -> list[str]:
    """A comma-separated list of names (blank entries dropped)."""
    return [n.strip() for n in text.split(",") if n.strip()]


def _effects(text: str) -> tuple[str, ...]:
    return tuple(_names(text))


def _add_ray(p: argparse.ArgumentParser, what: str) -> None:
    p.add_argument("--ray", metavar="ADDRESS",
                   help=f"run {what} as tasks on Ray (the optional `ray` extra): local (a Ray instance on this "
                   "machine's cores), auto (the cluster `ray start` made here, or $RAY_ADDRESS) or HOST:PORT; the "
                   "inputs and OUT must be on storage every worker mounts at the same path (docs/SCALING.md)")
    p.add_argument("--ray-retries", type=_non_negative_int, default=3,
                   help="with --ray: times a task is retried when its worker dies (default 3; a task that fails "
                   "on bad input is never retried)")


def add_synth(sub: argparse._SubParsersAction) -> None:
    from stgs.synth import PRESETS
    from stgs.synth.config import EFFECTS

    p = sub.add_parser("synth", help="generate a synthetic dynamic scene: ground truth + model dir",
                       description="Generate a procedural dynamic scene, render its ground-truth "
                       "multi-view images and fit a StreamSTGS model dir to it in parameter space.")
    p.add_argument("out", type=Path, help="output model dir (replaced if it is a model dir)")
    p.add_argument("--preset", choices=sorted(PRESETS), default="small",
                   help="base configuration (default: small)")
    p.add_argument("--config", type=Path, help="TOML file overriding SynthConfig fields")
    p.add_argument("--grid-side", type=_positive_int, help="S: capacity N = S² Gaussians")
    p.add_argument("--gops", type=_positive_int, dest="num_gops", help="number of GOPs")
    p.add_argument("--gop-size", type=_positive_int, help="frames per GOP")
    p.add_argument("--width", type=_positive_int, help="ground-truth image width")
    p.add_argument("--height", type=_positive_int, help="ground-truth image height")
    p.add_argument("--cameras", type=_positive_int, dest="num_cameras", help="ground-truth cameras")
    p.add_argument("--fit-steps", type=int, help="Adam steps of the parameter fit per GOP")
    p.add_argument("--feature-smoothness", type=float,
                   help="weight of the fit's feature roughness term, grid and time neighbours (default 0.3; "
                   "0: off, noise-like features that cost several times the bits)")
    p.add_argument("--seed", type=int, help="random seed")
    p.add_argument("--effects", type=_effects,
                   help=f"comma-separated effects to simulate (known: {','.join(EFFECTS)}; static_background "
                   "makes a layered scene, model format 2)")
    p.add_argument("--static-grid-side", type=_positive_int,
                   help="S_s: Gaussians S_s² of the static layer with static_background (default 32)")
    p.add_argument("--fold", action="store_true", default=None,
                   help="with static_background: fold the backdrop into every GOP (the same scene as a "
                   "single-layer, format-1 model, to compare with the layered one)")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.set_defaults(run=run_synth)


def synth_config_from_args(args: argparse.Namespace):
    from stgs.synth import PRESETS, config_from_toml

    cfg = PRESETS[args.preset]
    if args.config:
        cfg = config_from_toml(args.config, cfg)
    overrides = {f.name: getattr(args, f.name) for f in dataclasses.fields(cfg)
                 if getattr(args, f.name, None) is not None}
    cfg = dataclasses.replace(cfg, **overrides)
    cfg.validate()
    return cfg


def run_synth(args: argparse.Namespace) -> int:
    cfg = synth_config_from_args(args)  # a mistake is reported before the generator loads
    from stgs.synth import synthesize

    report = synthesize(cfg, args.out, progress=not args.quiet)
    layered = "static_background" in cfg.effects and not cfg.fold
    static = f" + a static layer of {cfg.static_grid_side ** 2}" if layered else ""
    if cfg.fold:
        static = f" (backdrop of {cfg.static_grid_side ** 2} folded into every GOP)"
    print(f"wrote {args.out}: {cfg.grid_side ** 2} Gaussians{static}, {cfg.num_gops} GOPs x "
          f"{cfg.gop_size} frames, effects {','.join(cfg.effects) or 'none'}")
    print(f"fidelity of the model vs ground truth: {report.fidelity_psnr:.2f} dB PSNR "
          f"over {report.fidelity_views} views")
    return 0


def _qps(text: str) -> tuple[int, ...]:
    try:
        return tuple(int(q) for q in text.split(",") if q.strip())
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a comma-separated list of integers: {text!r}") from None


def add_pack(sub: argparse._SubParsersAction) -> None:
    from stgs.codec.video import DEFAULT_QPS, PRESETS

    p = sub.add_parser("pack", help="package a model dir as an MPEG-DASH tree",
                       description="PLAS-sort each GOP, write its keyframe segment (lossless JPEG XL "
                       "attribute images + weights) and its feature video at every QP, then the MPD.")
    p.add_argument("model_dir", type=Path, help="model dir (stgs synth / stgs train output)")
    p.add_argument("out_dir", type=Path, help="output folder (a DASH tree any static server can serve)")
    p.add_argument("--qps", type=_qps, default=DEFAULT_QPS,
                   help=f"comma-separated feature-video QPs (default: {','.join(map(str, DEFAULT_QPS))})")
    p.add_argument("--preset", choices=PRESETS, default="medium", help="x265 preset (default: medium)")
    p.add_argument("--codec", default="hevc", help="feature-video codec (default and only: hevc)")
    p.add_argument("--jobs", type=_positive_int, help="parallel encodes (default: core count)")
    p.add_argument("--no-sort", action="store_true", help="skip the PLAS sort (for comparisons)")
    _add_ray(p, "one task per GOP (sort, keyframe) and per GOP x QP (encode, measure)")
    p.add_argument("--resume", action="store_true",
                   help="reuse segments a previous interrupted run of the same inputs completed")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(run=run_pack)


def run_pack(args: argparse.Namespace) -> int:
    from stgs.packager import MANIFEST, PackConfig, pack

    cfg = PackConfig(qps=args.qps, preset=args.preset, codec=args.codec, sort=not args.no_sort,
                     resume=args.resume)
    if args.jobs:
        cfg.jobs = args.jobs
    stats = pack(args.model_dir, args.out_dir, cfg, progress=not args.quiet, ray=args.ray,
                 retries=args.ray_retries)
    print(f"wrote {args.out_dir / MANIFEST}: {len(stats['gops'])} GOPs, keyframes "
          f"{stats['keyframe_bandwidth'] / 1e3:.0f} kbit/s")
    if static := stats.get("static"):
        print(f"  static layer: {static['capacity']} Gaussians, {static['bytes'] / 1e3:.1f} kB once")
    for rid, rep in stats["representations"].items():
        print(f"  {rid}: {rep['bandwidth'] / 1e3:8.0f} kbit/s  features {rep['mean_feature_psnr']:.2f} dB  "
              f"rendered {rep['mean_render_psnr']:.2f} dB")
    return 0


def add_serve(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("serve", help="serve packaged scenes over HTTP (DASH)",
                       description="Serve the DASH trees under ROOT (byte ranges, ETag/304, CORS, "
                       "immutable segments) with a scene catalogue at / and /scenes, /healthz and /metrics.")
    p.add_argument("root", type=Path, help="folder of packaged scenes (or one packaged scene)")
    p.add_argument("--host", default="127.0.0.1", help="listen address (default: 127.0.0.1)")
    p.add_argument("--port", type=int, default=8080, help="listen port (default: 8080; 0 picks one)")
    p.add_argument("--max-transfers", type=_positive_int, default=512,
                   help="file transfers in flight at once, server-wide (default: 512)")
    p.add_argument("--max-transfers-per-client", type=_positive_int, default=32,
                   help="file transfers in flight at once from one client address (default: 32)")
    p.add_argument("--max-connections-per-client", type=_non_negative_int, default=128,
                   help="open connections one client address may hold (default: 128; 0: no limit)")
    p.add_argument("--send-timeout", type=_positive_seconds, default=30.0,
                   help="seconds a transfer may go without the client taking a byte (default: 30)")
    p.add_argument("--shutdown-timeout", type=_positive_seconds, default=10.0,
                   help="on SIGTERM, seconds in-flight transfers get before they are cut (default: 10)")
    p.add_argument("--workers", type=_positive_int, default=1,
                   help="server processes sharing the port (default: 1; up to one per core)")
    p.add_argument("--io-threads", type=_non_negative_int, default=0,
                   help="threads for file stat/open (default: 0, on the event loop; more for network storage)")
    p.add_argument("--quiet", action="store_true", help="no access log")
    p.set_defaults(run=run_serve)


def run_serve(args: argparse.Namespace) -> int:
    from stgs.server.config import ServeConfig
    from stgs.server.workers import run

    if not args.root.is_dir():
        raise UsageError(f"{args.root}: not a folder")
    if not 0 <= args.port <= 65535:
        raise UsageError(f"--port must be in 0..65535, got {args.port}")
    run(ServeConfig(root=args.root, host=args.host, port=args.port, max_transfers=args.max_transfers,
                    max_transfers_per_client=args.max_transfers_per_client,
                    max_connections_per_client=args.max_connections_per_client, send_timeout=args.send_timeout,
                    shutdown_timeout=args.shutdown_timeout, workers=args.workers, io_threads=args.io_threads,
                    access_log=not args.quiet))
    return 0


def _vector(text: str) -> tuple[float, float, float]:
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        values = ()
    if len(values) != 3 or not all(map(math.isfinite, values)):
        raise argparse.ArgumentTypeError(f"expected three finite numbers x,y,z, got {text!r}")
    return values


def _size(text: str) -> tuple[int, int]:
    w, sep, h = text.lower().partition("x")
    if not (sep and w.isdigit() and h.isdigit() and int(w) > 0 and int(h) > 0):
        raise argparse.ArgumentTypeError(f"expected WIDTHxHEIGHT, e.g. 640x360, got {text!r}")
    return int(w), int(h)


def _seconds_parser(positive: bool):
    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"not a number of seconds: {text!r}") from None
        if not math.isfinite(value) or value < 0 or (positive and value == 0):
            words = "positive" if positive else "non-negative"
            raise argparse.ArgumentTypeError(f"must be a {words} number of seconds: {text!r}")
        return value

    return parse


_seconds = _seconds_parser(positive=False)
_positive_seconds = _seconds_parser(positive=True)


def add_play(sub: argparse._SubParsersAction) -> None:
    from stgs.client.abr import RULES
    from stgs.client.clock import RENDER_AHEAD
    from stgs.model.precision import PRECISIONS

    p = sub.add_parser("play", help="stream a packaged scene over HTTP and render it on the CPU",
                       description="Stream a StreamSTGS scene from its MPD URL: the ABR rule picks each GOP's "
                       "feature QP, the next GOP is downloaded while the current one plays, its feature video is "
                       "decoded frame by frame just ahead of the renderer, and every frame is deformed and "
                       "splatted on the CPU. Writes a JSON playback log.")
    p.add_argument("url", help="URL of the scene's manifest.mpd (http:// or https://)")
    p.add_argument("--abr", choices=sorted(RULES), default="mpc",
                   help="ABR rule (default: mpc = look-ahead over the next GOPs' sizes and PSNR from stats.json; "
                   "dynamic = dash.js's throughput / BOLA-E collection)")
    p.add_argument("--qp", type=int, help="pin the feature Representation of this QP (no adaptation)")
    p.add_argument("--buffer", type=_seconds, help="seconds to buffer ahead (default: three GOPs)")
    p.add_argument("--start", type=_seconds, default=0.0, help="start at the GOP holding this time (seconds)")
    p.add_argument("--duration", type=_seconds, help="seconds to play (default: to the end)")
    p.add_argument("--realtime", action="store_true",
                   help="pace frames to the clock and drop the ones rendering cannot make "
                   "(default: render every frame as fast as possible)")
    view = p.add_argument_group("viewpoint (default: an orbit inside the capture rig, or framing the scene)")
    view.add_argument("--camera", help="a camera of the scene by name (from cameras.json beside the MPD)")
    view.add_argument("--path", default="orbit",
                      help="'orbit' or a JSON file listing cameras (Camera.to_json) played in turn")
    view.add_argument("--orbit-seconds", type=_seconds, help="seconds per orbit turn (default: the whole playback)")
    view.add_argument("--eye", type=_vector, help="explicit camera position x,y,z (with --target)")
    view.add_argument("--target", type=_vector, default=(0.0, 0.0, 0.0), help="point the --eye camera looks at")
    view.add_argument("--fov", type=float, default=60.0, help="horizontal field of view, degrees (default: 60)")
    view.add_argument("--size", type=_size, help="image size WIDTHxHEIGHT (default: the camera's, else 640x360)")
    p.add_argument("--precision", choices=PRECISIONS, default="fp32",
                   help="arithmetic of the deformation network: bf16 is faster on CPUs with AVX512-BF16 "
                   "or AMX, int16 on AVX2 CPUs; both cost accuracy (docs/BENCHMARKS.md; default: fp32)")
    frame = p.add_argument_group("frame path (docs/CLIENT.md, 'Real-time playback')")
    frame.add_argument("--ring-frames", type=_positive_int, default=8,
                       help="feature frames decoded ahead of the renderer (default: 8; at least the model's window)")
    frame.add_argument("--render-ahead", type=_non_negative_int, default=RENDER_AHEAD,
                       help="with --realtime, frame slots a frame may be rendered before its own: absorbs frames "
                       f"slower than a slot, at that many frames of camera latency (default: {RENDER_AHEAD}; 0: none)")
    frame.add_argument("--render-threads", type=_positive_int,
                       help="threads of the deform and splat kernels (default: every usable core)")
    frame.add_argument("--decode-threads", type=_positive_int,
                       help="threads of the feature video decoder (default: 1 below eight cores, else 2)")
    p.add_argument("--out", type=Path, help="write frames: a folder of PNGs, or a .mp4 file")
    p.add_argument("--log", type=Path, help="JSON playback log (default: playback.json beside --out, else none)")
    p.add_argument("--timeout", type=_seconds, default=10.0, help="seconds without data before a request fails")
    p.add_argument("--retries", type=int, default=3, help="retries per request (default: 3)")
    urls = p.add_argument_group("URL policy (default: http(s) from the manifest's host and the hosts its BaseURLs "
                                "name; no link-local addresses; loopback only for a manifest on loopback)")
    urls.add_argument("--allow-host", action="append", default=[], metavar="HOST",
                      help="also fetch from this host, e.g. a CDN the server redirects to (repeatable)")
    urls.add_argument("--allow-any-host", action="store_true", help="fetch from any host (address rules still hold)")
    urls.add_argument("--allow-loopback", action="store_true", help="allow loopback addresses for a remote manifest")
    urls.add_argument("--allow-link-local", action="store_true",
                      help="allow link-local addresses (169.254.0.0/16, fe80::/10; cloud metadata lives there)")
    p.set_defaults(run=run_play)


def run_play(args: argparse.Namespace) -> int:
    import asyncio

    from stgs.client import PlayConfig, play
    from stgs.client.download import DownloadSettings
    from stgs.client.urlpolicy import UrlPolicySettings
    from stgs.client.view import ViewSpec

    if not args.url.startswith(("http://", "https://")):
        raise UsageError(f"{args.url}: the manifest URL must start with http:// or https://")
    if args.retries < 0 or args.timeout <= 0:
        raise UsageError("--retries must be >= 0 and --timeout > 0")
    if not 1 <= args.fov < 180:
        raise UsageError("--fov must be in [1, 180) degrees")
    width, height = args.size or (None, None)
    view = ViewSpec(camera=args.camera, eye=args.eye, target=args.target, path=args.path,
                    orbit_seconds=args.orbit_seconds, width=width, height=height, fov_deg=args.fov)
    log = args.log
    if log is None and args.out is not None:
        log = (args.out.parent if args.out.suffix.lower() == ".mp4" else args.out) / "playback.json"
    cfg = PlayConfig(url=args.url, abr=args.abr, qp=args.qp, buffer_s=args.buffer, start_s=args.start,
                     duration_s=args.duration, realtime=args.realtime, view=view, out=args.out, log=log,
                     precision=args.precision, ring_frames=args.ring_frames, render_ahead=args.render_ahead,
                     render_threads=args.render_threads,
                     decode_threads=args.decode_threads,
                     download=DownloadSettings(read_timeout_s=args.timeout, retries=args.retries),
                     urls=UrlPolicySettings(hosts=tuple(args.allow_host), any_host=args.allow_any_host,
                                            loopback=True if args.allow_loopback else None,
                                            link_local=args.allow_link_local))
    summary = asyncio.run(play(cfg))
    print_playback(summary)
    if log is not None:
        print(f"playback log: {log}")
    return 0


def print_playback(s: dict) -> None:
    qps = ",".join(str(g["qp"]) for g in s["gops"])
    print(f"played {s['gops_played']} GOP(s), {s['frames']} frames, start-up {s['startup_delay_s']:.2f} s, "
          f"QPs {qps}, {s['switches']} switch(es)")
    print(f"stalls {s['stalls']['count']} ({s['stalls']['total_s']:.2f} s), dropped frames {s['dropped_frames']}, "
          f"{s['kb_per_frame']:.1f} KB/frame, render {s['render_ms_median'] or 0:.1f} ms/frame median")


def add_train(sub: argparse._SubParsersAction) -> None:
    from stgs.train.config import BUDGETS

    p = sub.add_parser("train", help="train a StreamSTGS model dir from multi-view video (CPU)",
                       description="Per-GOP StreamSTGS training: triangulated initial points, a coarse canonical "
                       "stage, then per GOP canonical Gaussians + temporal features + deformation field with the "
                       "paper's losses, relocation and pruning. Writes a model dir `stgs pack` accepts.")
    p.add_argument("dataset", type=Path, help="Panoptic folder (train_meta.json), N3DV folder "
                   "(poses_bounds.npy + cam*.mp4) or a stgs synth model dir")
    p.add_argument("out", type=Path, help="output model dir")
    p.add_argument("--budget", choices=sorted(BUDGETS), default="quick",
                   help="quick (CI, minutes), cpu (a 60-frame GOP at 640x360 in ~1 h), paper (12k it, ~150k Gaussians)")
    p.add_argument("--kind", choices=["auto", "panoptic", "n3dv", "synth"], default="auto", help="dataset layout")
    p.add_argument("--holdout", type=_names, help="comma-separated validation cameras (default: the dataset's)")
    p.add_argument("--gops", type=_positive_int, dest="max_gops", help="train at most this many GOPs")
    p.add_argument("--gop-size", type=_positive_int, help="frames per GOP (default 60)")
    p.add_argument("--start-frame", type=int, help="first frame")
    p.add_argument("--grid-side", type=_positive_int,
                   help="S: capacity N = S² Gaussians per GOP (layered: of the dynamic layer)")
    p.add_argument("--layers", choices=["single", "layered"],
                   help="single (default): every GOP holds every Gaussian, model format 1; layered: a static layer "
                   "fitted once (stage A) + smaller per-GOP dynamic layers (stage B), model format 2, which "
                   "`stgs pack` cannot carry yet")
    p.add_argument("--static-grid-side", type=_positive_int,
                   help="S_s: Gaussians S_s² of the static layer (layered; default: the budget's)")
    p.add_argument("--no-migrate", dest="migrate", action="store_false", default=None,
                   help="layered: static Gaussians the data shows moving stay static (no migration)")
    p.add_argument("--static-sh", type=int, choices=[0, 1], dest="static_sh_degree",
                   help="layered: view-dependent colour of the static layer, 0 (default) none, 1 a degree-1 term "
                   "fitted after stage A")
    p.add_argument("--static-sh-iterations", type=int,
                   help="layered, --static-sh 1: iterations of that fit (default 500)")
    p.add_argument("--iterations", type=_positive_int, help="iterations per GOP")
    p.add_argument("--coarse-iterations", type=int,
                   help="iterations of the coarse canonical stage (layered: of stage A, the static layer)")
    p.add_argument("--position-lr", type=float,
                   help="initial position learning rate × the scene extent (decays 100× over a stage; "
                   "default: the budget's)")
    p.add_argument("--scale", type=float, help="training image scale (0.5 = half size)")
    p.add_argument("--window", type=_positive_int, help="sliding window W (default 3)")
    p.add_argument("--background-share", type=float,
                   help="share of the Gaussians first placed on the walls and floor of a rig that surrounds the "
                   "scene (default: the budget's, 0.5 for cpu and paper, 0 for quick; 0 turns it off)")
    p.add_argument("--init-frames", type=_positive_int,
                   help="frames spread over the trained span whose views are triangulated for the initial points "
                   "(default 6; 1: the first frame only)")
    p.add_argument("--no-aux", dest="aux", action="store_false", default=None,
                   help="no transformer-guided auxiliary pass")
    p.add_argument("--no-dynamic-density", dest="dynamic", action="store_false", default=None,
                   help="no extra loss on dynamic pixels")
    p.add_argument("--no-temporal-reg", dest="temporal_weight", action="store_const", const=0.0,
                   help="no temporal Huber consistency of features")
    p.add_argument("--no-relocate", dest="relocate", action="store_false", default=None,
                   help="no relocation of dead Gaussians")
    p.add_argument("--seed", type=int, help="random seed (default 0)")
    p.add_argument("--threads", type=_positive_int,
                   help="torch threads (default: torch's; with --ray, 1 per task). The same seed and threads give "
                   "the same bytes, locally or on Ray")
    _add_ray(p, "the base stage, then one task per GOP,")
    p.add_argument("--resume", action="store_true", help="continue an interrupted run from its checkpoints")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.set_defaults(run=run_train)


TRAIN_OVERRIDES = ("max_gops", "gop_size", "start_frame", "grid_side", "iterations", "coarse_iterations", "scale",
                   "window", "aux", "dynamic", "temporal_weight", "relocate", "seed", "threads", "holdout",
                   "background_share", "init_frames", "layers", "static_grid_side", "migrate",
                   "static_sh_degree", "static_sh_iterations")


def train_overrides(args: argparse.Namespace) -> dict:
    """TrainConfig fields the command line sets (the rest come from the budget)."""
    from stgs.train.config import BUDGETS

    overrides = {k: getattr(args, k) for k in TRAIN_OVERRIDES if getattr(args, k) is not None}
    if args.position_lr is not None:  # TrainConfig.validate checks the rates
        overrides["lr"] = dataclasses.replace(BUDGETS[args.budget].lr, position=args.position_lr,
                                              position_final=args.position_lr / 100)
    return overrides


def run_train(args: argparse.Namespace) -> int:
    from stgs.train import budget

    cfg = budget(args.budget, **train_overrides(args))  # a mistake is reported before the trainer loads
    from stgs.train import train

    report = train(args.dataset, args.out, cfg, progress=not args.quiet, resume=args.resume, kind=args.kind,
                   ray=args.ray, retries=args.ray_retries)
    for g in report["gops"]:
        val = f", validation {g['val_psnr']:.2f} dB" if g["val_psnr"] is not None else ""
        print(f"GOP {g['gop']}: {g['iterations']} iterations in {g['seconds']:.0f} s, train {g['train_psnr']:.2f} dB"
              f"{val}, {g['relocated']} relocated, {g['pruned']} pruned")
    if "static_capacity" in report:
        print(f"static layer: {report['static_capacity']} Gaussians in {report['static_seconds']:.0f} s "
              f"(moving pixels from {report['moving_mask_source']}; {report['migrated']} Gaussians migrated to the "
              "dynamic layers)")
    print(f"wrote {args.out} ({report['capacity']} Gaussians per GOP, {len(report['gops'])} GOP(s))")
    return 0


def add_eval(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("eval", help="PSNR/SSIM of a model dir (and its packaged stream) on held-out cameras",
                       description="Render the validation cameras of every GOP from the uncompressed model and, "
                       "with --dash, from every Representation of its DASH tree; compare with the dataset.")
    p.add_argument("model_dir", type=Path, help="model dir (stgs train output)")
    p.add_argument("dataset", type=Path, help="the dataset it was trained on")
    p.add_argument("--dash", type=Path, help="the model's packaged tree (stgs pack output) to evaluate per QP")
    p.add_argument("--holdout", type=_names, help="validation cameras (default: those the model was trained without)")
    p.add_argument("--stride", type=_positive_int, default=1, help="evaluate every n-th frame (default: 1)")
    p.add_argument("--out", type=Path, help="where eval.json and eval_grid.png go (default: MODEL_DIR)")
    p.add_argument("--lpips", choices=["alex", "vgg", "off"], default="alex",
                   help="LPIPS network, computed only where torchvision's cache ($TORCH_HOME/hub/checkpoints) "
                   "already holds its ImageNet backbone; nothing is downloaded (default: alex)")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.set_defaults(run=run_eval)


def run_eval(args: argparse.Namespace) -> int:
    from stgs.evaluate import evaluate

    result = evaluate(args.model_dir, args.dataset, args.out or args.model_dir, args.dash, args.holdout,
                      args.stride, progress=not args.quiet, lpips_net=None if args.lpips == "off" else args.lpips)
    for name, stream in result["streams"].items():
        regions = (f" (foreground {stream['psnr_foreground']:.2f} dB, background {stream['psnr_background']:.2f} dB)"
                   if "psnr_foreground" in stream and "psnr_background" in stream else "")
        lpips = f", LPIPS ({args.lpips}) {stream['lpips']:.4f}" if "lpips" in stream else ""
        print(f"{name}: PSNR {stream['psnr']:.2f} dB{regions}, SSIM {stream['ssim']:.4f}{lpips} over "
              f"{len(stream['gops'])} GOP(s)")
    if result["lpips"] and not result["lpips"]["computed"]:
        print(f"LPIPS not computed: {result['lpips']['reason']}")
    print(f"wrote {(args.out or args.model_dir) / 'eval.json'}")
    return 0


def add_sim(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("sim", help="throughput simulation: how a scene streams over a network with an ABR rule",
                       description="Run a scenario (TOML: scene, ABR rules, buffer, effects such as bandwidth "
                       "traces, latency, jitter, loss, outages, competing clients) on the discrete-event simulator "
                       "and/or the emulator (the real player and server through a shaping proxy); write QoE "
                       "reports, per-GOP timelines and plots.")
    p.add_argument("scenario", type=Path, help="scenario file (TOML; see docs/HARNESS.md)")
    p.add_argument("--engine", choices=["sim", "emulate", "both"], default="sim",
                   help="sim: virtual clock (fast); emulate: real player + server in real time; both")
    p.add_argument("--traces", type=Path, help="batch: run the scenario once per trace file in this folder")
    p.add_argument("--load", help="load mode: comma-separated client counts against one real server")
    p.add_argument("--decode", action="store_true", help="emulate: decode and render too (default: network only)")
    p.add_argument("--speed", type=float, default=1.0,
                   help="emulate: run the player's clock and the network this many times faster than real time "
                   "(without --decode; default 1)")
    p.add_argument("--export-sabre", type=Path, help="also write the scene's ladder as Sabre's manifest JSON")
    p.add_argument("--out", type=Path, default=Path("sim-output"), help="output folder (default: ./sim-output)")
    p.set_defaults(run=run_sim)


def run_sim(args: argparse.Namespace) -> int:
    from stgs.harness.scenario import load_scenario

    sc = load_scenario(args.scenario)  # before the heavy imports: a mistake in it is reported at once
    from stgs.harness.ladder import load_ladder
    from stgs.harness.report import sabre_manifest, summary_table, write_json
    from stgs.harness.runner import run_batch, run_load, run_scenario

    args.out.mkdir(parents=True, exist_ok=True)
    if args.export_sabre:
        write_json(args.export_sabre, sabre_manifest(load_ladder(sc.scene)))
        print(f"wrote {args.export_sabre}")
    engines = ["sim", "emulate"] if args.engine == "both" else [args.engine]
    print(f"scenario {sc.name}: active effects {sc.effects.describe() or 'none'}")
    if args.load:
        rows = run_load(sc, _int_list(args.load, "--load"), args.out)
        print((args.out / f"{sc.name}.load.md").read_text().rstrip())
        return 0 if rows else 1
    if not (args.speed > 0 and math.isfinite(args.speed)) or (args.speed != 1 and args.decode):
        raise UsageError("--speed must be positive, and other than 1 only without --decode")
    rows = run_batch(sc, args.traces, engines, args.out, args.speed) if args.traces else run_scenario(
        sc, engines, args.out, args.decode, args.speed)
    print(summary_table(rows))
    print(f"wrote reports to {args.out}/")
    return 0


def add_demo(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("demo", help="run the end-to-end demo on the embedded default scene",
                       description="Synthesise the default scene, render a free-viewpoint orbit "
                       "from the model and write frames, a contact sheet and a fidelity summary.")
    p.add_argument("--out", type=Path, default=Path("demo-output"),
                   help="output folder (default: ./demo-output)")
    p.add_argument("--fit-steps", type=int, default=None,
                   help="Adam steps per GOP when fitting the scene (default: the demo preset's 400; "
                   "150 takes under half the time for a rougher model, about 43 dB against 53.6)")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.set_defaults(run=run_demo)


def run_demo(args: argparse.Namespace) -> int:
    from stgs.cli.demo import run

    return run(args.out, progress=not args.quiet, fit_steps=args.fit_steps)


def add_bench(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("bench", help="benchmarks (accuracy vs time), printed as a Markdown table",
                       description="Run a benchmark suite and print Markdown for docs/BENCHMARKS.md.")
    p.add_argument("suite", choices=["render", "synth", "pack", "serve", "play", "sim", "abr", "train"],
                   help="render: splatter and deform per backend and Gaussian count; "
                   "synth: fit fidelity vs fit iterations; pack: rate, distortion and codec time per "
                   "QP and x265 preset, PLAS vs no sort, PLAS time; serve: stgs serve vs nginx with wrk; "
                   "play: real-time playback (bench/realtime.py: drops, stalls, per-frame decode, wait, deform "
                   "and splat, start-up, seek, peak memory per QP); "
                   "sim: simulated vs emulated QoE and playbacks per second; abr: every ABR rule over trace "
                   "sets at 6 s and 25 s of buffer, and the ladder floor; train: held-out quality vs "
                   "training time of finished stgs train runs (--runs)")
    p.add_argument("--sizes", default="16384,65536,147456",
                   help="comma-separated Gaussian counts (default: 16384,65536,147456)")
    p.add_argument("--width", type=_positive_int, default=640)
    p.add_argument("--height", type=_positive_int, default=360)
    p.add_argument("--repeats", type=_positive_int, default=5, help="timed runs per measurement")
    p.add_argument("--reference-max", type=int, default=65536,
                   help="render: skip the reference backends above this many Gaussians (time)")
    p.add_argument("--steps", default="25,50,100,200,400,800",
                   help="synth: comma-separated fit steps per GOP (default: 25,50,100,200,400,800)")
    p.add_argument("--preset", default="small", help="synth: SynthConfig preset (default: small)")
    p.add_argument("--smoothness", help="synth: comma-separated feature smoothness weights to compare in feature "
                   "bits and decode time per QP of --qps, instead of the fit-steps table")
    p.add_argument("--qps", default="16,20,24,28,32", help="pack, play: QPs (default: 16,20,24,28,32)")
    p.add_argument("--presets", default="ultrafast,veryfast,medium,slow",
                   help="pack: x265 presets (default: ultrafast,veryfast,medium,slow)")
    p.add_argument("--sides", default="128,256,384", help="pack: PLAS grid sides S (default: 128,256,384)")
    p.add_argument("--scene", help="pack, play: synthetic scene preset to pack (default: demo)")
    p.add_argument("--dash", type=Path,
                   help="serve, play, sim, abr: a packaged scene (default: synthesise and pack one)")
    p.add_argument("--clients", default="1,16,64,256", help="serve: concurrent clients (default: 1,16,64,256)")
    p.add_argument("--seconds", type=_positive_int, default=8, help="serve: seconds per measurement (default: 8)")
    p.add_argument("--runs", help="train: comma-separated model dirs written by stgs train (and stgs eval)")
    p.add_argument("--plot", type=Path, help="pack, train: where to write the plot (default: "
                   "docs/rate_distortion.png, docs/train_curves.png)")
    p.set_defaults(run=run_bench)


def _int_list(text: str, option: str) -> list[int]:
    try:
        values = [int(s) for s in text.split(",") if s]
    except ValueError:
        raise UsageError(f"{option} must be comma-separated integers, got {text!r}") from None
    if not values or min(values) < 0:
        raise UsageError(f"{option} must list non-negative integers, got {text!r}")
    return values


def _float_list(text: str | None, option: str) -> list[float]:
    if not text:
        return []
    try:
        values = [float(s) for s in text.split(",") if s]
    except ValueError:
        raise UsageError(f"{option} must be comma-separated numbers, got {text!r}") from None
    if not all(0 <= v < 1e6 for v in values):
        raise UsageError(f"{option} must list numbers in [0, 1e6), got {text!r}")
    return values


def bench_suite(name: str):
    """The module bench/<name>.py of the source checkout (the benchmarks are not installed with the package)."""
    root = Path(__file__).resolve().parents[1]
    if not (root / "bench" / f"{name}.py").is_file():
        raise UsageError("stgs bench runs from a source checkout: its bench/ folder is not installed")
    if str(root) not in sys.path:
        sys.path.insert(0, str(root))
    return importlib.import_module(f"bench.{name}")


def run_bench(args: argparse.Namespace) -> int:
    from stgs.synth import PRESETS
    from stgs.tree import MANIFEST

    # Every flag is checked before the suite (torch and the rest) loads: a mistake is reported at once.
    if args.dash is not None and not (args.dash / MANIFEST).is_file():
        raise UsageError(f"--dash {args.dash}: no {MANIFEST} there")
    if args.suite == "train" and not args.runs:
        raise UsageError("bench train needs --runs DIR[,DIR...] (model dirs of finished stgs train runs)")
    name = "realtime" if args.suite == "play" else args.suite
    if args.suite == "train":
        return bench_suite(name).main([Path(d) for d in args.runs.split(",") if d],
                                      args.plot or Path("docs/train_curves.png"))
    if args.suite in ("sim", "abr"):
        return bench_suite(name).main(args.dash)
    if args.suite == "serve":
        clients = _int_list(args.clients, "--clients")
        return bench_suite(name).main(args.dash, clients, args.seconds)
    scene = args.scene or "demo"
    if scene not in PRESETS:
        raise UsageError(f"--scene must be one of {', '.join(sorted(PRESETS))}")
    if args.suite == "play":
        qps = _int_list(args.qps, "--qps")
        return bench_suite(name).cli(args.dash, PRESETS[scene], qps, args.width, args.height)
    if args.suite == "pack":
        from stgs.codec.video import PRESETS as X265_PRESETS

        presets = [p for p in args.presets.split(",") if p]
        unknown = sorted(set(presets) - set(X265_PRESETS))
        if unknown:
            raise UsageError(f"--presets: unknown x265 preset(s) {unknown}")
        qps, sides = _int_list(args.qps, "--qps"), _int_list(args.sides, "--sides")
        return bench_suite(name).main(qps, presets, sides, args.plot or Path("docs/rate_distortion.png"),
                                      PRESETS[scene])
    if args.suite == "synth":
        if args.preset not in PRESETS:
            raise UsageError(f"--preset must be one of {', '.join(sorted(PRESETS))}")
        steps, smoothness = _int_list(args.steps, "--steps"), _float_list(args.smoothness, "--smoothness")
        qps = _int_list(args.qps, "--qps")
        return bench_suite(name).main(steps, args.preset, smoothness, qps)
    sizes = _int_list(args.sizes, "--sizes")
    return bench_suite(name).main(sizes, args.width, args.height, args.repeats, args.reference_max)


COMMANDS = {"synth": add_synth, "train": add_train, "eval": add_eval, "pack": add_pack, "serve": add_serve,
            "play": add_play, "sim": add_sim, "demo": add_demo, "bench": add_bench}


def build_parser(commands: tuple[str, ...] | None = None) -> argparse.ArgumentParser:
    """The stgs parser; `commands` limits it to some subcommands (the server image has no torch)."""
    parser = argparse.ArgumentParser(prog="stgs", description="StreamSTGS: streamable free-viewpoint video.")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name in commands or tuple(COMMANDS):
        COMMANDS[name](sub)
    return parser


def main(argv: list[str] | None = None, commands: tuple[str, ...] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if commands is None and argv and argv[0] in COMMANDS:
        commands = (argv[0],)  # only that command's parser: `stgs serve` imports nothing of torch
    args = build_parser(commands).parse_args(argv)
    try:
        return args.run(args)
    except FieldError as exc:
        print(f"stgs: {FLAGS.get(exc.field, exc.field)} {exc.message}", file=sys.stderr)
        return 2
    except StgsError as exc:
        print(f"stgs: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:  # unwritable output, missing file, full disk: the user's environment
        where = f": {exc.filename}" if exc.filename else ""
        print(f"stgs: {exc.strerror or exc}{where}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("stgs: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
