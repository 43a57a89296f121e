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


def add_pack(sub: argparse._SubParsersAction) -> None:
    from stgs.codec.quant import KEYFRAME_RUNGS
    from stgs.codec.video import AV1, CODECS, HEVC, LADDERS, PRESETS

    p = sub.add_parser("pack", help="package a model dir as an MPEG-DASH tree",
                       description="PLAS-sort each GOP, write its keyframe segments (JPEG XL attribute images + "
                       "weights: lossless, and on an auto ladder the lossy keyframe rungs) and its feature video at "
                       "every ladder point of each codec (12-bit HEVC, 10-bit AV1 for browsers), measure every "
                       "rung, then write the MPD.")
    p.add_argument("model_dir", type=Path, help="model dir (stgs synth / stgs train output)")
    p.add_argument("out_dir", type=Path, help="output folder (a DASH tree any static server can serve)")
    p.add_argument("--ladder", choices=LADDERS,
                   help="auto: pick each codec's rungs by measured rendered quality from its candidate QPs; fixed: "
                   "every QP given is a rung (default: auto, or fixed when --qps or --av1-qps is given; "
                   "docs/PACKAGING.md, 'The auto ladder')")
    p.add_argument("--qps", type=qp_list,
                   help=f"comma-separated HEVC feature-video QPs: the rungs of a fixed ladder, the candidates of an "
                   f"auto one (default: {','.join(map(str, HEVC.ladder))} fixed, "
                   f"{','.join(map(str, HEVC.candidates))} auto)")
    p.add_argument("--preset", choices=PRESETS, default="medium", help="x265 preset (default: medium)")
    p.add_argument("--codecs", type=codec_list, default=tuple(CODECS),
                   help=f"comma-separated feature-video codecs, one AdaptationSet each (default: "
                   f"{','.join(CODECS)}; either alone allowed)")
    p.add_argument("--av1-qps", type=qp_list,
                   help=f"comma-separated AV1 QPs, 1..63, as --qps (default: {','.join(map(str, AV1.ladder))} "
                   f"fixed: about the bytes of the fixed HEVC QPs; {','.join(map(str, AV1.candidates))} auto)")
    lossy = [name for name in KEYFRAME_RUNGS if name != "lossless"]
    p.add_argument("--keyframe-rungs", type=keyframe_rung_list, default=tuple(lossy), metavar="RUNGS",
                   help=f"comma-separated lossy keyframe rungs ({', '.join(lossy)}) an auto ladder may pair a feature "
                   f"rung with, or 'none' (default: {','.join(lossy)}; docs/PACKAGING.md, 'Keyframe rungs', says "
                   "what they save and what measuring them costs)")
    p.add_argument("--av1-preset", choices=AV1.presets, default=AV1.default_preset,
                   help=f"SVT-AV1 preset, 0 slowest .. 13 fastest (default: {AV1.default_preset})")
    p.add_argument("--no-loop-filters", action="store_true",
                   help="encode without HEVC's deblocking and SAO filters (the decoder then skips them; "
                   "docs/PACKAGING.md weighs bytes, PSNR and decode time)")
    p.add_argument("--jobs", type=positive_int, help="parallel encodes (default: core count)")
    p.add_argument("--no-sort", action="store_true", help="skip the PLAS sort (for comparisons)")
    add_ray(p, "one task per GOP (sort, keyframe) and per GOP x ladder point (encode, measure)")
    p.add_argument("--resume", action="store_true",
                   help="reuse segments a previous interrupted run of the same inputs completed")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(run=run_pack)


def run_pack(args: argparse.Namespace) -> int:
    from stgs.packager import MANIFEST, PackConfig, pack

    given = args.qps is not None or args.av1_qps is not None
    ladder = args.ladder or ("fixed" if given else "auto")
    cfg = PackConfig(ladder=ladder, qps=args.qps, preset=args.preset, loop_filters=not args.no_loop_filters,
                     codecs=args.codecs, av1_qps=args.av1_qps, av1_preset=args.av1_preset, sort=not args.no_sort,
                     resume=args.resume, keyframe_rungs=args.keyframe_rungs)
    if args.jobs:
        cfg.jobs = args.jobs
    stats = pack(args.model_dir, args.out_dir, cfg, progress=not args.quiet, ray=args.ray,
                 retries=args.ray_retries)
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
    p.add_argument("--host", default="127.0.0.1", help="listen address (default: 127.0.0.1)")
    p.add_argument("--port", type=int, default=8080, help="listen port (default: 8080; 0 picks one)")
    p.add_argument("--max-transfers", type=positive_int, default=512,
                   help="file transfers sending at once, server-wide (default: 512)")
    p.add_argument("--max-transfers-per-client", type=positive_int,
                   help="file transfers sending at once for one client address, at most a quarter of "
                        "--max-transfers (default: 32, or that quarter when smaller)")
    p.add_argument("--max-waiting-transfers", type=positive_int, default=1024,
                   help="transfers parked on a client that takes no bytes (they hold no slot); one more cuts "
                        "the one with the least recent progress (default: 1024)")
    p.add_argument("--trusted-proxy", action="append", default=[], metavar="CIDR",
                   help="a proxy's address range whose X-Forwarded-For / Forwarded name the client, for the "
                        "per-client limits (repeatable; without it those headers are ignored)")
    p.add_argument("--max-connections-per-client", type=non_negative_int, default=128,
                   help="open connections one client address may hold (default: 128; 0: no limit)")
    p.add_argument("--send-timeout", type=positive_seconds, default=30.0,
                   help="seconds a transfer may go without the client taking a byte (default: 30)")
    p.add_argument("--shutdown-timeout", type=positive_seconds, default=10.0,
                   help="on SIGTERM, seconds in-flight transfers get before they are cut (default: 10)")
    p.add_argument("--workers", type=positive_int, default=1,
                   help="server processes sharing the port (default: 1; up to one per core)")
    p.add_argument("--io-threads", type=non_negative_int, default=0,
                   help="threads for file stat/open (default: 0, on the event loop; more for network storage)")
    p.add_argument("--player-dir", type=Path,
                   help="the built web player to serve at /player/ (default: web/dist of this checkout)")
    p.add_argument("--quiet", action="store_true", help="no access log")
    p.set_defaults(run=run_serve)


def serve_config(args: argparse.Namespace):
    """The ServeConfig of parsed `stgs serve` flags (its checks raise FieldError, naming the setting)."""
    from stgs.server.config import ServeConfig

    return ServeConfig(root=args.root, host=args.host, port=args.port, max_transfers=args.max_transfers,
                       max_transfers_per_client=args.max_transfers_per_client,
                       max_waiting_transfers=args.max_waiting_transfers, trusted_proxies=tuple(args.trusted_proxy),
                       max_connections_per_client=args.max_connections_per_client, send_timeout=args.send_timeout,
                       shutdown_timeout=args.shutdown_timeout, workers=args.workers, io_threads=args.io_threads,
                       player_dir=args.player_dir, access_log=not args.quiet)


def run_serve(args: argparse.Namespace) -> int:
    from stgs.server.workers import run

    if not args.root.is_dir():
        raise UsageError(f"{args.root}: not a folder")
    if not 0 <= args.port <= 65535:
        raise UsageError(f"--port must be in 0..65535, got {args.port}")
    if args.player_dir is not None and not (args.player_dir / "index.html").is_file():
        raise UsageError(f"--player-dir {args.player_dir}: no index.html there "
                         "(build the player: cd web && npm run build)")
    run(serve_config(args))
    return 0


def add_play(sub: argparse._SubParsersAction) -> None:
    from stgs.client.abr import RULES
    from stgs.client.clock import RENDER_AHEAD
    from stgs.model.precision import PRECISIONS
    from stgs.mpd_profile import FEATURE_CODEC_CHOICES

    p = sub.add_parser("play", help="stream a packaged scene over HTTP and render it on the CPU",
                       description="Stream a StreamSTGS scene from its MPD URL: the ABR rule picks each GOP's "
                       "feature QP, the next GOP is downloaded while the current one plays, its feature video is "
                       "decoded frame by frame just ahead of the renderer, and every frame is deformed and "
                       "splatted on the CPU. Writes a JSON playback log.")
    p.add_argument("url", help="URL of the scene's manifest.mpd (http:// or https://)")
    p.add_argument("--abr", choices=sorted(RULES), default="mpc",
                   help="ABR rule (default: mpc = look-ahead over the next GOPs' sizes and PSNR from stats.json; "
                   "dynamic = dash.js's throughput / BOLA-E collection)")
    p.add_argument("--qp", type=int, help="pin the feature Representation of this ladder point: an HEVC QP, or "
                   "with --codec av1 an AV1 QP (no adaptation)")
    p.add_argument("--codec", choices=FEATURE_CODEC_CHOICES, default="auto",
                   help="feature set to play: auto (HEVC where the tree has it, else AV1), hevc (12-bit) or av1 "
                   "(10-bit, the browsers' set; default: auto)")
    p.add_argument("--buffer", type=seconds, help="seconds to buffer ahead (default: three GOPs)")
    p.add_argument("--start", type=seconds, default=0.0, help="start at the GOP holding this time (seconds)")
    p.add_argument("--duration", type=seconds, help="seconds to play (default: to the end)")
    p.add_argument("--realtime", action="store_true",
                   help="pace frames to the clock and drop the ones rendering cannot make "
                   "(default: render every frame as fast as possible)")
    view = p.add_argument_group("viewpoint (default: an orbit inside the capture rig, or framing the scene)")
    view.add_argument("--camera", help="a camera of the scene by name (from cameras.json beside the MPD)")
    view.add_argument("--path", default="orbit",
                      help="'orbit' or a JSON file listing cameras (Camera.to_json) played in turn")
    view.add_argument("--orbit-seconds", type=seconds, help="seconds per orbit turn (default: the whole playback)")
    view.add_argument("--eye", type=vector3, help="explicit camera position x,y,z (with --target)")
    view.add_argument("--target", type=vector3, default=(0.0, 0.0, 0.0), help="point the --eye camera looks at")
    view.add_argument("--fov", type=float, default=60.0, help="horizontal field of view, degrees (default: 60)")
    view.add_argument("--size", type=image_size, help="image size WIDTHxHEIGHT (default: the camera's, else 640x360)")
    p.add_argument("--precision", choices=PRECISIONS, default="fp32",
                   help="arithmetic of the deformation network: bf16 is faster on CPUs with AVX512-BF16 "
                   "or AMX, int16 on AVX2 CPUs; both cost accuracy (docs/BENCHMARKS.md; default: fp32)")
    frame = p.add_argument_group("frame path (docs/CLIENT.md, 'Real-time playback')")
    frame.add_argument("--ring-frames", type=positive_int, default=8,
                       help="feature frames decoded ahead of the renderer (default: 8; at least the model's window)")
    frame.add_argument("--render-ahead", type=non_negative_int, default=RENDER_AHEAD,
                       help="with --realtime, frame slots a frame may be rendered before its own: absorbs frames "
                       f"slower than a slot, at that many frames of camera latency (default: {RENDER_AHEAD}; 0: none)")
    frame.add_argument("--render-threads", type=positive_int,
                       help="threads of the deform and splat kernels (default: every usable core)")
    frame.add_argument("--decode-threads", type=positive_int,
                       help="threads of the feature video decoder (default: 1 below eight cores, else 2)")
    p.add_argument("--out", type=Path, help="write frames: a folder of PNGs, or a .mp4 file")
    p.add_argument("--log", type=Path, help="JSON playback log (default: playback.json beside --out, else none)")
    p.add_argument("--timeout", type=seconds, default=10.0, help="seconds without data before a request fails")
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
    cfg = PlayConfig(url=args.url, abr=args.abr, qp=args.qp, codec=args.codec, buffer_s=args.buffer,
                     start_s=args.start,
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
    reps = ",".join(str(g["rep"]) for g in s["gops"])
    codec = f"{s['codec']} " if "codec" in s else ""
    print(f"played {s['gops_played']} GOP(s), {s['frames']} frames, start-up {s['startup_delay_s']:.2f} s, "
          f"{codec}rungs {reps}, {s['switches']} switch(es)")
    print(f"stalls {s['stalls']['count']} ({s['stalls']['total_s']:.2f} s), dropped frames {s['dropped_frames']}, "
          f"{s['kb_per_frame']:.1f} KB/frame, render {s['render_ms_median'] or 0:.1f} ms/frame median")
