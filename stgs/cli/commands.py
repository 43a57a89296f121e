"""The `stgs` command: one entry point, one subcommand per pipeline stage.

The subcommands live by stage: `capture` (inspect), `model` (synth, train, eval), `stream` (pack,
serve, play), `study` (sim, demo, bench) and `interop` (export); `args` holds their argument
parsers. User mistakes (bad paths, bad configs, bad input files) raise the
library's StgsError, or the command line's UsageError for a bad combination
of flags, and end as one `stgs: ...` line on stderr with exit status 2; a
FieldError names a config field, which the flag declared for it names here
(stgs.cli.config_flags.flag_of). Anything else is a bug and keeps its traceback.
"""

from __future__ import annotations

import argparse
import sys

from stgs.cli.capture import add_inspect, add_prepare
from stgs.cli.config_flags import flag_of
from stgs.cli.interop import add_export
from stgs.cli.model import add_eval, add_synth, add_train
from stgs.cli.stream import add_pack, add_play, add_serve
from stgs.cli.study import add_bench, add_demo, add_sim
from stgs.errors import FieldError, StgsError

COMMANDS = {"prepare": add_prepare, "inspect": add_inspect, "synth": add_synth, "train": add_train, "eval": add_eval,
            "pack": add_pack, "serve": add_serve, "play": add_play, "sim": add_sim, "demo": add_demo,
            "bench": add_bench, "export": add_export}


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
        print(f"stgs: {flag_of(exc.field)} {exc.message}", file=sys.stderr)
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
