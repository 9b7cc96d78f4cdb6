"""`soma`: the command-line entry point.

Each subcommand lives in its own module under :mod:`soma_ros.commands` and
exposes ``register(subparsers)``, which adds its parser and sets
``func=run``. Modules are imported lazily so `soma --help` stays fast and a
missing optional dependency of one command does not break the others.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from typing import Optional, Sequence

from . import __version__
from .core.errors import SomaError

#: (subcommand name, module under soma_ros.commands, one-line help)
COMMANDS: list[tuple[str, str, str]] = [
    ("world", "world", "generate reference-world episodes (MuJoCo) recorded as rosbags"),
    ("robot", "robot", "inspect a robot URDF: chain, limits, end-effector and control points"),
    ("scene", "scene", "make, inspect or convert a splat scene (.ply / .splat)"),
    ("reconstruct", "reconstruct", "build the initial splat scene from bags or a multi-view capture"),
    ("dataset", "dataset", "check / inspect a folder of recordings before training"),
    ("train", "train", "fit the simulator offline from rosbags"),
    ("eval", "eval", "evaluate a checkpoint on a dataset (open-loop rollouts)"),
    ("resim", "resim", "open-loop resimulation of one bag, without ROS running"),
    ("view", "view", "a live 3D view of the twin in the browser (splats, robot, cameras)"),
    ("discrepancy", "discrepancy", "find and name effects missing from the model"),
    ("config", "config", "the configuration reference, and configs with their bases applied"),
    ("bench", "bench", "benchmarks (speed, memory, accuracy)"),
]


def _load(module: str):
    return importlib.import_module(f"soma_ros.commands.{module}")


def build_parser(argv: Optional[Sequence[str]] = None) -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="soma",
        description="soma_ros: a learned real-to-sim simulator of soft-body manipulation, served on ROS 2.",
    )
    parser.add_argument("--version", action="version", version=f"soma_ros {__version__}")
    parser.add_argument("--debug", action="store_true", help="show the traceback of an error")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    wanted = next((a for a in argv if not a.startswith("-")), None) if argv else None
    for name, module, help_text in COMMANDS:
        if wanted != name:
            # Only import the module that is asked for (none for `soma --help`): the others get a
            # stub parser, enough for the command list.
            sub.add_parser(name, help=help_text, add_help=False)
            continue
        try:
            mod = _load(module)
        except ModuleNotFoundError as exc:
            if exc.name and exc.name.startswith("soma_ros.commands"):
                continue  # command not built yet in this version
            raise
        mod.register(sub)
    return parser


def main(argv: Optional[Sequence[str]] = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = build_parser(argv)
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 0 if not args.command else 2
    try:
        rc = args.func(args)
    except KeyboardInterrupt:
        print("soma: interrupted", file=sys.stderr)
        return 130
    except (SomaError, OSError, ValueError, RuntimeError) as exc:
        # User-facing errors: one line naming the problem, exit code 2; --debug shows the traceback.
        if args.debug:
            raise
        print(f"soma {args.command}: error: {' '.join(str(exc).split()) or type(exc).__name__}", file=sys.stderr)
        return 2
    return int(rc or 0)


if __name__ == "__main__":
    sys.exit(main())
