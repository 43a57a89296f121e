"""The command line's own vocabulary: argument parsers of the stgs subcommands and UsageError."""

from __future__ import annotations

import argparse
import math

from stgs.errors import StgsError


class UsageError(StgsError):
    """Flags that do not go together or do not parse (the CLI's own error)."""


def int_at_least(lowest: int, words: str):
    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"not an integer: {text!r}") from None
        if value < lowest:
            raise argparse.ArgumentTypeError(f"must be {words}: {value}")
        return value

    return parse


positive_int = int_at_least(1, "positive")


non_negative_int = int_at_least(0, "0 or more")


def name_list(text: str) -> list[str]:
    """A comma-separated list of names (blank entries dropped)."""
    return [n.strip() for n in text.split(",") if n.strip()]


def name_number(text: str, flag: str) -> tuple[str, float]:
    """`flag`'s NAME=NUMBER (the name is checked by whoever takes it); parsed after argparse, so that a mistake
    is one line."""
    name, sep, value = text.partition("=")
    try:
        number = float(value)
    except ValueError:
        number = None
    if not (sep and name.strip()) or number is None:
        raise UsageError(f"{flag} expects NAME=NUMBER, got {text!r}")
    return name.strip(), number


def effect_list(text: str) -> tuple[str, ...]:
    return tuple(name_list(text))


def qp_list(text: str) -> tuple[int, ...]:
    try:
        return tuple(int(q) for q in text.split(",") if q.strip())
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a comma-separated list of integers: {text!r}") from None


def codec_list(text: str) -> tuple[str, ...]:
    """Comma-separated feature-video codec names (stgs.codec.video.CODECS)."""
    from stgs.codec.video import CODECS

    names = tuple(c.strip() for c in text.split(",") if c.strip())
    unknown = [c for c in names if c not in CODECS]
    if not names or unknown or len(set(names)) != len(names):
        raise argparse.ArgumentTypeError(f"expected distinct codecs of {', '.join(CODECS)}, got {text!r}")
    return names


def keyframe_rung_list(text: str) -> tuple[str, ...]:
    """Comma-separated lossy keyframe rungs (stgs.codec.quant.KEYFRAME_RUNGS but the lossless one), or `none`."""
    from stgs.codec.quant import KEYFRAME_RUNGS

    if text.strip() == "none":
        return ()
    lossy = [name for name in KEYFRAME_RUNGS if name != "lossless"]
    names = tuple(c.strip() for c in text.split(",") if c.strip())
    if not names or set(names) - set(lossy) or len(set(names)) != len(names):
        raise argparse.ArgumentTypeError(f"expected distinct rungs of {', '.join(lossy)}, or none, got {text!r}")
    return names


def vector3(text: str) -> tuple[float, float, float]:
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        values = ()
    if len(values) != 3 or not all(map(math.isfinite, values)):
        raise argparse.ArgumentTypeError(f"expected three finite numbers x,y,z, got {text!r}")
    return values


def image_size(text: str) -> tuple[int, int]:
    w, sep, h = text.lower().partition("x")
    if not (sep and w.isdigit() and h.isdigit() and int(w) > 0 and int(h) > 0):
        raise argparse.ArgumentTypeError(f"expected WIDTHxHEIGHT, e.g. 640x360, got {text!r}")
    return int(w), int(h)


BYTE_UNITS = {"": 1, "k": 1 << 10, "m": 1 << 20, "g": 1 << 30, "t": 1 << 40}


def byte_size(text: str) -> int:
    """A size in bytes: a number with an optional binary unit, e.g. 512M, 1.5G, 2GiB, 4096."""
    body = text.strip().lower().removesuffix("ib").removesuffix("b")
    unit = body[-1:] if body[-1:] in BYTE_UNITS else ""
    try:
        value = float(body[: len(body) - len(unit)])
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a size: {text!r} (e.g. 512M, 2G)") from None
    if not math.isfinite(value) or value < 0:
        raise argparse.ArgumentTypeError(f"must be a size of 0 or more: {text!r}")
    return int(value * BYTE_UNITS[unit])


def seconds_parser(positive: bool):
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


seconds = seconds_parser(positive=False)


positive_seconds = seconds_parser(positive=True)


def positive_float(text: str) -> float:
    """A finite number above 0 (a frame rate)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"must be a positive number: {text!r}")
    return value


def int_list(text: str, option: str) -> list[int]:
    try:
        values = [int(s) for s in text.split(",") if s]
    except ValueError:
        raise UsageError(f"{option} must be comma-separated integers, got {text!r}") from None
    if not values or min(values) < 0:
        raise UsageError(f"{option} must list non-negative integers, got {text!r}")
    return values


def float_list(text: str | None, option: str) -> list[float]:
    if not text:
        return []
    try:
        values = [float(s) for s in text.split(",") if s]
    except ValueError:
        raise UsageError(f"{option} must be comma-separated numbers, got {text!r}") from None
    if not all(0 <= v < 1e6 for v in values):
        raise UsageError(f"{option} must list numbers in [0, 1e6), got {text!r}")
    return values


def add_ray(p: argparse.ArgumentParser, what: str) -> None:
    p.add_argument("--ray", metavar="ADDRESS",
                   help=f"run {what} as tasks on Ray (the optional `ray` extra): local (a Ray instance on this "
                   "machine's cores), auto (the cluster `ray start` made here, or $RAY_ADDRESS) or HOST:PORT; the "
                   "inputs and OUT must be on storage every worker mounts at the same path (docs/SCALING.md)")
    p.add_argument("--ray-retries", type=non_negative_int, default=3,
                   help="with --ray: times a task is retried when its worker dies (default 3; a task that fails "
                   "on bad input is never retried)")
