"""Subcommands that study the system: `stgs sim`, `stgs demo`, `stgs bench`."""

from __future__ import annotations

import argparse
import importlib
import math
import sys
from pathlib import Path

from stgs.cli.args import UsageError, float_list, int_list, positive_int


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
        rows = run_load(sc, int_list(args.load, "--load"), args.out)
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
                   help="Adam steps per GOP when fitting the scene (default: the demo preset's; fewer fit a rougher "
                   "model sooner: the README's demo section gives the figures)")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.set_defaults(run=run_demo)


def run_demo(args: argparse.Namespace) -> int:
    from stgs.cli.demo import run

    return run(args.out, progress=not args.quiet, fit_steps=args.fit_steps)


SUITES = {"render": "frame.render", "synth": "training.synth", "pack": "packaging.pack", "serve": "serving.serve",
          "play": "playback.realtime", "sim": "streaming.sim", "abr": "streaming.abr", "train": "training.train"}
"""`stgs bench SUITE` -> the benchmark it runs (bench/GROUP/NAME.py)."""


def add_bench(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("bench", help="benchmarks (accuracy vs time), printed as a Markdown table",
                       description="Run a benchmark suite and print Markdown for docs/BENCHMARKS.md.")
    p.add_argument("suite", choices=list(SUITES),
                   help="render: splatter and deform per backend and Gaussian count; "
                   "synth: fit fidelity vs fit iterations; pack: rate, distortion and codec time per "
                   "QP and x265 preset, PLAS vs no sort, PLAS time; serve: stgs serve vs nginx with wrk; "
                   "play: real-time playback (bench/playback/realtime.py: drops, stalls, per-frame decode, wait, "
                   "deform "
                   "and splat, start-up, seek, peak memory per QP); "
                   "sim: simulated vs emulated QoE and playbacks per second; abr: every ABR rule over trace "
                   "sets (generated, or recorded with --traces) at 6 s and 25 s of buffer, each rule's paired "
                   "difference from the best classic rule, and the ladder floor; train: held-out quality vs "
                   "training time of finished stgs train runs (--runs)")
    p.add_argument("--sizes", default="16384,65536,147456",
                   help="comma-separated Gaussian counts (default: 16384,65536,147456)")
    p.add_argument("--width", type=positive_int, default=640)
    p.add_argument("--height", type=positive_int, default=360)
    p.add_argument("--repeats", type=positive_int,
                   help="timed runs per measurement (render: default 5; play: start-up and seek runs, default 3)")
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
    p.add_argument("--traces", help="abr: comma-separated folders of recorded traces (Mahimahi, Pensieve or Sabre "
                   "JSON files, the format sniffed per file), one trace set each, instead of the generated sets")
    p.add_argument("--against", type=Path,
                   help="abr: a second packaging of --dash's model (e.g. its auto ladder) played on the same "
                   "generated traces: rendered PSNR, bytes and rebuffering of both")
    p.add_argument("--latency-ms", type=float, default=40.0,
                   help="abr: round-trip time of the recorded sets of --traces (default: 40)")
    p.add_argument("--no-trace-scale", action="store_true",
                   help="abr: play --traces at their recorded rates (default: each set scaled by one constant so "
                   "that its median trace's mean equals the top rung)")
    p.add_argument("--clients", default="1,16,64,256", help="serve: concurrent clients (default: 1,16,64,256)")
    p.add_argument("--seconds", type=positive_int, default=8, help="serve: seconds per measurement (default: 8)")
    p.add_argument("--runs", help="train: comma-separated model dirs written by stgs train (and stgs eval)")
    p.add_argument("--plot", type=Path, help="pack, train: where to write the plot (default: "
                   "docs/rate_distortion.png, docs/train_curves.png)")
    p.set_defaults(run=run_bench)


def bench_suite(suite: str):
    """The benchmark module of `suite` in the source checkout (the benchmarks are not installed with the package)."""
    root = Path(__file__).resolve().parents[2]
    name = SUITES[suite]
    if not (root / "bench" / f"{name.replace('.', '/')}.py").is_file():
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
    name = args.suite
    if args.suite == "train":
        return bench_suite(name).main([Path(d) for d in args.runs.split(",") if d],
                                      args.plot or Path("docs/train_curves.png"))
    if args.suite == "abr":
        folders = [Path(d) for d in (args.traces or "").split(",") if d]
        for folder in folders:
            if not folder.is_dir():
                raise UsageError(f"--traces {folder}: not a folder")
        if not math.isfinite(args.latency_ms) or args.latency_ms < 0:
            raise UsageError("--latency-ms must be a non-negative number")
        if args.against is not None:
            if args.dash is None or folders:
                raise UsageError("--against compares with --dash, on the generated traces (not --traces)")
            if not (args.against / MANIFEST).is_file():
                raise UsageError(f"--against {args.against}: no {MANIFEST} there")
            return bench_suite(name).compare_ladders(args.dash, args.against)
        return bench_suite(name).main(args.dash, folders or None, args.latency_ms, not args.no_trace_scale)
    if args.suite == "sim":
        return bench_suite(name).main(args.dash)
    if args.suite == "serve":
        clients = int_list(args.clients, "--clients")
        return bench_suite(name).main(args.dash, clients, args.seconds)
    scene = args.scene or "demo"
    if scene not in PRESETS:
        raise UsageError(f"--scene must be one of {', '.join(sorted(PRESETS))}")
    if args.suite == "play":
        qps = int_list(args.qps, "--qps")
        return bench_suite(name).cli(args.dash, PRESETS[scene], qps, args.width, args.height, args.repeats or 3)
    if args.suite == "pack":
        from stgs.codec.video import PRESETS as X265_PRESETS

        presets = [p for p in args.presets.split(",") if p]
        unknown = sorted(set(presets) - set(X265_PRESETS))
        if unknown:
            raise UsageError(f"--presets: unknown x265 preset(s) {unknown}")
        qps, sides = int_list(args.qps, "--qps"), int_list(args.sides, "--sides")
        return bench_suite(name).main(qps, presets, sides, args.plot or Path("docs/rate_distortion.png"),
                                      PRESETS[scene])
    if args.suite == "synth":
        if args.preset not in PRESETS:
            raise UsageError(f"--preset must be one of {', '.join(sorted(PRESETS))}")
        steps, smoothness = int_list(args.steps, "--steps"), float_list(args.smoothness, "--smoothness")
        qps = int_list(args.qps, "--qps")
        return bench_suite(name).main(steps, args.preset, smoothness, qps)
    sizes = int_list(args.sizes, "--sizes")
    return bench_suite(name).main(sizes, args.width, args.height, args.repeats or 5, args.reference_max)
