"""Subcommands that package, serve and play a scene: `stgs pack`, `stgs serve`, `stgs play`."""

from __future__ import annotations

import argparse
from pathlib import Path

from stgs.cli.args import (
    UsageError,
    add_ray,
    codec_list,
    image_size,
    keyframe_rung_list,
    non_negative_int,
    positive_int,
    positive_seconds,
    qp_list,
    seconds,
    vector3,
)
from stgs.cli.config_flags import ConfigFlag, add_config_flags, build_config, config_values


def add_pack(sub: argparse._SubParsersAction) -> None:
    from stgs.packager import PackConfig

    p = sub.add_parser("pack", help="package a model dir as an MPEG-DASH tree",
                       description="PLAS-sort each GOP, write its keyframe segments (JPEG XL attribute images + "
                       "weights: lossless, and on an auto ladder the lossy keyframe rungs) and its feature video at "
                       "every ladder point of each codec (12-bit HEVC, 10-bit AV1 for browsers), measure every "
                       "rung, then write the MPD.")
    p.add_argument("model_dir", type=Path, help="model dir (stgs synth / stgs train output)")
    p.add_argument("out_dir", type=Path, help="output folder (a DASH tree any static server can serve)")
    add_config_flags(p, PackConfig, pack_flags())
    add_ray(p, "one task per GOP (sort, keyframe) and per GOP x ladder point (encode, measure)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(run=run_pack)


def pack_flags() -> tuple[ConfigFlag, ...]:
    """The PackConfig fields `stgs pack` sets."""
    from stgs.codec.video import AV1, LADDERS, PRESETS

    return (
        ConfigFlag("ladder", choices=LADDERS, default_note="auto, or fixed when --qps or --av1-qps is given"),
        ConfigFlag("qps", type=qp_list),
        ConfigFlag("preset", choices=PRESETS),
        ConfigFlag("codecs", type=codec_list),
        ConfigFlag("av1_qps", type=qp_list),
        ConfigFlag("keyframe_rungs", type=keyframe_rung_list, metavar="RUNGS"),
        ConfigFlag("av1_preset", choices=AV1.presets),
        ConfigFlag("loop_filters", "--no-loop-filters", off=True),
        ConfigFlag("jobs", type=positive_int, default_note="the core count"),
        ConfigFlag("sort", "--no-sort", off=True),
        ConfigFlag("resume", on=True),
        ConfigFlag("title", default_note="the model dir's name"),
        ConfigFlag("description"),
        ConfigFlag("poster", "--no-poster", off=True),
    )


def run_pack(args: argparse.Namespace) -> int:
    from stgs.packager import MANIFEST, PackConfig, pack

    values = config_values(args, pack_flags())
    if "ladder" not in values and ("qps" in values or "av1_qps" in values):
        values["ladder"] = "fixed"  # points given on their own are the rungs
    cfg = build_config(PackConfig, values)
    stats = pack(args.model_dir, args.out_dir, cfg, progress=not args.quiet, ray=args.ray,
                 retries=args.ray_retries)
    if stats.get("still"):
        static, views = stats["static"], stats["quality_views"]
        print(f"wrote {args.out_dir / MANIFEST}: a still scene, its static layer alone ({static['capacity']} "
              f"Gaussians, {static['bytes'] / 1e3:.1f} kB; rendered {static['render_psnr']:.2f} dB against the "
              f"uncompressed layer at {len(views['cameras'])} {views['source']} camera(s))")
        return 0
    print(f"wrote {args.out_dir / MANIFEST}: {len(stats['gops'])} GOPs, keyframes "
          f"{stats['keyframe_bandwidth'] / 1e3:.0f} kbit/s")
    for rep, info in stats.get("keyframe_representations", {}).items():
        print(f"  keyframe rung {rep}: {info['bandwidth'] / 1e3:.0f} kbit/s ({info['quant']})")
    if static := stats.get("static"):
        print(f"  static layer: {static['capacity']} Gaussians, {static['bytes'] / 1e3:.1f} kB once")
    views = stats["quality_views"]
    print(f"  rendered PSNR against the uncompressed model at {len(views['cameras'])} {views['source']} camera(s) x "
          f"{len(views['frames'])} frame(s) per GOP")
    for codec, ladder in stats["ladders"].items():
        print(f"  {codec} ({ladder['mode']} ladder):")
        for cand in ladder["candidates"]:
            rid = cand["representation"]
            if not cand["kept"]:
                print(f"    {rid:>24}  dropped: {cand['reason']}")
                continue
            rep = stats["representations"][cand.get("features", rid)]
            truth = f"  vs capture {rep['mean_truth_psnr']:.2f} dB" if "mean_truth_psnr" in rep else ""
            kbps = cand["total_bytes"] * 8 / (len(stats["gops"]) * stats["segment_seconds"]) / 1e3
            print(f"    {rid:>24}  {kbps:6.0f} kbit/s with keyframes  features {rep['mean_feature_psnr']:.2f} dB  "
                  f"rendered {rep['mean_render_psnr']:.2f} dB{truth}  ({cand['reason']})")
    return 0


def add_serve(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("serve", help="serve packaged scenes over HTTP (DASH)",
                       description="Serve the DASH trees under ROOT (byte ranges, ETag/304, CORS, "
                       "immutable segments) with a scene catalogue at / and /scenes, the web player at /player/, "
                       "/healthz and /metrics.")
    p.add_argument("root", type=Path, help="folder of packaged scenes (or one packaged scene)")
    from stgs.server.config import ServeConfig

    add_config_flags(p, ServeConfig, SERVE_FLAGS)
    p.add_argument("--quiet", action="store_true", help="no access log")
    p.set_defaults(run=run_serve)


SERVE_FLAGS = (
    ConfigFlag("host"),
    ConfigFlag("port"),
    ConfigFlag("max_transfers", type=positive_int),
    ConfigFlag("max_transfers_per_client", type=positive_int),
    ConfigFlag("max_waiting_transfers", type=positive_int),
    ConfigFlag("trusted_proxies", "--trusted-proxy", repeat=True, metavar="CIDR"),
    ConfigFlag("max_connections_per_client", type=non_negative_int),
    ConfigFlag("send_timeout", type=positive_seconds),
    ConfigFlag("shutdown_timeout", type=positive_seconds),
    ConfigFlag("workers", type=positive_int),
    ConfigFlag("io_threads", type=non_negative_int),
    ConfigFlag("player_dir"),
)
"""The ServeConfig fields `stgs serve` sets."""


def serve_config(args: argparse.Namespace):
    """The ServeConfig of parsed `stgs serve` flags (its checks raise FieldError, naming the setting)."""
    from stgs.server.config import ServeConfig

    values = config_values(args, SERVE_FLAGS) | ({"access_log": False} if args.quiet else {})
    return build_config(ServeConfig, values, root=args.root)


def run_serve(args: argparse.Namespace) -> int:
    from stgs.server.workers import run

    if not args.root.is_dir():
        raise UsageError(f"{args.root}: not a folder")
    if args.port is not None and not 0 <= args.port <= 65535:
        raise UsageError(f"--port must be in 0..65535, got {args.port}")
    if args.player_dir is not None and not (args.player_dir / "index.html").is_file():
        raise UsageError(f"--player-dir {args.player_dir}: no index.html there "
                         "(build the player: cd web && npm run build)")
    run(serve_config(args))
    return 0


def play_flags() -> dict[str, tuple[ConfigFlag, ...]]:
    """The PlayConfig fields `stgs play` sets, by the help group they show in ("": the main one)."""
    from stgs.client.abr import RULES
    from stgs.model.precision import PRECISIONS
    from stgs.mpd.profile import FEATURE_CODEC_CHOICES

    return {
        "": (
            ConfigFlag("abr", choices=sorted(RULES)),
            ConfigFlag("qp"),
            ConfigFlag("codec", choices=FEATURE_CODEC_CHOICES),
            ConfigFlag("buffer_s", "--buffer", type=seconds),
            ConfigFlag("start_s", "--start", type=seconds),
            ConfigFlag("duration_s", "--duration", type=seconds),
            ConfigFlag("realtime", on=True),
            ConfigFlag("precision", choices=PRECISIONS),
            ConfigFlag("out"),
            ConfigFlag("log", default_note="playback.json beside --out, else none"),
            ConfigFlag("download.read_timeout_s", "--timeout", type=seconds),
            ConfigFlag("download.retries", type=non_negative_int),
        ),
        "viewpoint (default: an orbit inside the capture rig, or framing the scene)": (
            ConfigFlag("view.camera"),
            ConfigFlag("view.path"),
            ConfigFlag("view.orbit_seconds", type=seconds),
            ConfigFlag("view.eye", type=vector3, metavar="X,Y,Z"),
            ConfigFlag("view.target", type=vector3, metavar="X,Y,Z"),
            ConfigFlag("view.fov_deg", "--fov", type=float),
        ),
        "frame path (docs/CLIENT.md, 'Real-time playback')": (
            ConfigFlag("ring_frames", type=positive_int),
            ConfigFlag("render_ahead", type=non_negative_int),
            ConfigFlag("render_threads", type=positive_int),
            ConfigFlag("decode_threads", type=positive_int),
        ),
        "URL policy (default: http(s) from the manifest's host and the hosts its BaseURLs name; no link-local "
        "addresses; loopback only for a manifest on loopback)": (
            ConfigFlag("urls.hosts", "--allow-host", repeat=True, metavar="HOST"),
            ConfigFlag("urls.any_host", "--allow-any-host", on=True),
            ConfigFlag("urls.loopback", "--allow-loopback", on=True),
            ConfigFlag("urls.link_local", "--allow-link-local", on=True),
        ),
    }


def add_play(sub: argparse._SubParsersAction) -> None:
    from stgs.client import PlayConfig

    p = sub.add_parser("play", help="stream a packaged scene over HTTP and render it on the CPU",
                       description="Stream a StreamSTGS scene from its MPD URL: the ABR rule picks each GOP's "
                       "feature QP, the next GOP is downloaded while the current one plays, its feature video is "
                       "decoded frame by frame just ahead of the renderer, and every frame is deformed and "
                       "splatted on the CPU. Writes a JSON playback log.")
    p.add_argument("url", help="URL of the scene's manifest.mpd (http:// or https://)")
    groups = play_flags()
    every = [spec for specs in groups.values() for spec in specs]
    for title, specs in groups.items():
        group = p.add_argument_group(title) if title else p
        add_config_flags(group, PlayConfig, specs, every)
        if title.startswith("viewpoint"):
            group.add_argument("--size", type=image_size,
                               help="image size WIDTHxHEIGHT (default: the camera's, else 640x360)")
    p.set_defaults(run=run_play)


def run_play(args: argparse.Namespace) -> int:
    import asyncio

    from stgs.client import PlayConfig, play

    if not args.url.startswith(("http://", "https://")):
        raise UsageError(f"{args.url}: the manifest URL must start with http:// or https://")
    values = config_values(args, [spec for specs in play_flags().values() for spec in specs])
    if values.get("download.read_timeout_s", 1.0) <= 0:
        raise UsageError("--timeout must be > 0")
    if not 1 <= values.get("view.fov_deg", 60.0) < 180:
        raise UsageError("--fov must be in [1, 180) degrees")
    if args.size is not None:
        values["view.width"], values["view.height"] = args.size
    out = values.get("out")
    if "log" not in values and out is not None:
        values["log"] = (out.parent if out.suffix.lower() == ".mp4" else out) / "playback.json"
    cfg = build_config(PlayConfig, values, url=args.url)
    summary = asyncio.run(play(cfg))
    print_playback(summary)
    if cfg.log is not None:
        print(f"playback log: {cfg.log}")
    return 0


def print_playback(s: dict) -> None:
    if s.get("still"):
        render = f", render {max(s['render_ms']):.1f} ms/frame at most" if s["render_ms"] else ""
        print(f"showed a still scene: {s['frames']} frame(s), static layer {s['static_bytes'] / 1e3:.1f} kB in "
              f"{s['download_s']:.2f} s{render}")
        return
    reps = ",".join(str(g["rep"]) for g in s["gops"])
    codec = f"{s['codec']} " if "codec" in s else ""
    print(f"played {s['gops_played']} GOP(s), {s['frames']} frames, start-up {s['startup_delay_s']:.2f} s, "
          f"{codec}rungs {reps}, {s['switches']} switch(es)")
    print(f"stalls {s['stalls']['count']} ({s['stalls']['total_s']:.2f} s), dropped frames {s['dropped_frames']}, "
          f"{s['kb_per_frame']:.1f} KB/frame, render {s['render_ms_median'] or 0:.1f} ms/frame median")
