"""`soma bench`: benchmarks (speed, memory, accuracy).

Sub-commands are listed in :data:`SUBCOMMANDS` as (name, module, help); each
module exposes ``add_arguments(parser)`` and ``run(args) -> int``. Adding one
(e.g. ``accuracy``) is one more entry. The benchmark modules live in the
checkout's ``benchmarks/`` folder.
"""

from __future__ import annotations

import argparse
import importlib
import sys

from soma_ros.paths import PACKAGE_DIR

#: (sub-command, module with add_arguments/run, one-line help)
SUBCOMMANDS: list[tuple[str, str, str]] = [
    ("core", "benchmarks.bench_core", "simulator step time and render time vs splat count (cpu/paper models)"),
    ("accuracy", "benchmarks.bench_accuracy", "accuracy table (Table 1 form) with baselines on reference-world data"),
]


def _import(module: str):
    try:
        return importlib.import_module(module)
    except ModuleNotFoundError as exc:
        root = PACKAGE_DIR.parent
        if exc.name == module.split(".")[0] and (root / module.split(".")[0]).is_dir() and str(root) not in sys.path:
            sys.path.insert(0, str(root))
            return importlib.import_module(module)
        raise


def _unavailable(message: str):
    def run_unavailable(args: argparse.Namespace) -> int:
        raise RuntimeError(message)

    return run_unavailable


def register(subparsers) -> None:
    p = subparsers.add_parser("bench", help="benchmarks (speed, memory, accuracy)", description=__doc__.splitlines()[0])
    sub = p.add_subparsers(dest="bench_command", metavar="BENCH")
    for name, module, help_text in SUBCOMMANDS:
        sp = sub.add_parser(name, help=help_text, description=help_text)
        try:
            mod = _import(module)
        except ModuleNotFoundError as exc:
            err = f"`soma bench {name}` needs {module} (a soma_ros checkout): {exc}"
            sp.set_defaults(bench_func=_unavailable(err))
            continue
        mod.add_arguments(sp)
        sp.set_defaults(bench_func=mod.run)
    p.set_defaults(func=run, bench_parser=p)


def run(args: argparse.Namespace) -> int:
    func = getattr(args, "bench_func", None)
    if func is None:
        args.bench_parser.print_help()
        return 2
    return int(func(args) or 0)
