"""Accuracy benchmark: the form of the paper's Table 1 on reference-world data, with baselines.

    soma bench accuracy --preset tiny --out runs/accuracy              # rope, cloth, doll
    soma bench accuracy --preset tiny --objects rope --out runs/acc    # one object
    soma bench accuracy --preset tiny --jobs 2 --out runs/accuracy     # objects in 2 parallel processes
    python -m benchmarks.bench_accuracy --preset tiny --out runs/acc   # same, without the soma CLI

For each object: generate (or reuse) a reference-world dataset, train every
learned variant with ``soma train`` (full, state_only, img_only, no_mrt), fit
the spring-mass baseline, evaluate all of them, ``prior_only`` (full with the network off) and ``static`` on the training
(resimulation) and held-out (generalization) episodes, and write OUT/table.md,
OUT/table.json ({object: {variant: {split: {metric: value}}}}) and
OUT/bench.json. Presets: config/eval/<preset>.yaml (tiny: 2-core CPU, under
an hour per object; paper: the paper's scale, for a GPU). See
:mod:`soma_ros.evaluation.accuracy`.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from typing import Optional, Sequence

__all__ = ["add_arguments", "run", "register", "main"]


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--preset", default="tiny", help="config/eval/<preset>.yaml or a YAML path: tiny | paper (default: tiny)")
    p.add_argument("--objects", default=None, metavar="LIST",
                   help="comma-separated objects (default: the preset's: rope,cloth,doll)")
    p.add_argument("--variants", default=None, metavar="LIST",
                   help="comma-separated variants (default: full,prior_only,static,state_only,spring_mass,img_only,no_mrt)")
    p.add_argument("--out", required=True, metavar="DIR", help="output folder (data/, runs/, eval/, table.md, table.json)")
    p.add_argument("--episodes", type=int, default=None, metavar="N", help="episodes per object (default: the preset's)")
    p.add_argument("--seed", type=int, default=None, metavar="S", help="reference-world seed (default: the preset's)")
    p.add_argument("--fresh", action="store_true", help="start over (delete OUT/data, OUT/runs, OUT/eval)")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.add_argument("--jobs", type=int, default=1, metavar="N",
                   help="benchmark up to N objects at once, each in its own process (one torch thread each; "
                        "the slowest object of a previous run in OUT starts first); default 1")


def run(args: argparse.Namespace) -> int:
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    os.environ.setdefault("MUJOCO_GL", "egl")
    import dataclasses
    from pathlib import Path

    import torch

    torch.set_num_threads(int(os.environ.get("OMP_NUM_THREADS", "1") or 1))
    from soma_ros.evaluation.accuracy import load_bench_config, run_bench

    bench = load_bench_config(args.preset)
    if args.variants:
        bench = dataclasses.replace(bench, variants=[v.strip() for v in args.variants.split(",") if v.strip()])
    if args.episodes is not None or args.seed is not None:
        w = dataclasses.replace(bench.world, episodes=args.episodes if args.episodes is not None else bench.world.episodes,
                                seed=args.seed if args.seed is not None else bench.world.seed)
        bench = dataclasses.replace(bench, world=w)
    bench.validate()
    objects = [o.strip() for o in args.objects.split(",") if o.strip()] if args.objects else None
    if args.jobs < 1:
        raise ValueError(f"--jobs must be >= 1, got {args.jobs}")
    if args.jobs > 1 and len(objects or bench.objects) > 1:
        return _run_parallel(args, objects or list(bench.objects))
    t0 = time.time()
    res = run_bench(bench, Path(args.out), objects, fresh=args.fresh, progress=not args.quiet,
                    log=lambda s: print(s, flush=True))
    out = Path(args.out)
    print(f"soma bench accuracy: {', '.join(res['table'])} done in {(time.time() - t0) / 60:.1f} min")
    print(f"  wrote {out / 'table.md'}, {out / 'table.json'}, {out / 'bench.json'}")
    for obj, m in res["meta"]["objects"].items():
        for c in m.get("comparison_test", []):
            print(f"  {obj}: held-out {c['metric']}: full {c['full']:.4f} vs {c['baseline']} {c['baseline_value']:.4f} "
                  f"({'better' if c['full_better'] else 'NOT better'})")
    return 0


def _run_parallel(args: argparse.Namespace, objects: list[str]) -> int:
    """One child process per object (``--objects OBJ``), at most ``args.jobs`` at once; the children
    merge their rows into OUT/table.json (see :func:`soma_ros.evaluation.accuracy._write`)."""
    import json
    import subprocess
    from pathlib import Path

    out = Path(args.out)
    if args.fresh and out.exists():
        import shutil

        for sub in ("data", "runs", "eval", "table.json", "table.md", "bench.json"):
            target = out / sub
            shutil.rmtree(target, ignore_errors=True) if target.is_dir() else target.unlink(missing_ok=True)
    before = {}
    try:
        before = {o: float(m.get("seconds", 0)) for o, m in json.loads((out / "bench.json").read_text())["objects"].items()}
    except (OSError, ValueError, KeyError, TypeError):
        pass
    order = sorted(objects, key=lambda o: -before.get(o, 0.0))  # slowest first (stable: as given otherwise)
    base = [sys.executable, "-m", "benchmarks.bench_accuracy", "--preset", args.preset, "--out", str(out)]
    for flag, val in (("--variants", args.variants), ("--episodes", args.episodes), ("--seed", args.seed)):
        if val is not None:
            base += [flag, str(val)]
    if args.quiet:
        base.append("--quiet")
    t0 = time.time()
    print(f"soma bench accuracy: {len(order)} objects in up to {args.jobs} processes: {', '.join(order)}", flush=True)
    running: list[tuple[str, subprocess.Popen]] = []
    failed = []
    pending = list(order)
    while pending or running:
        while pending and len(running) < args.jobs:
            o = pending.pop(0)
            running.append((o, subprocess.Popen(base + ["--objects", o])))
        time.sleep(1.0)
        for o, proc in list(running):
            if proc.poll() is not None:
                running.remove((o, proc))
                if proc.returncode != 0:
                    failed.append(o)
                print(f"soma bench accuracy: {o} finished (exit {proc.returncode}) at "
                      f"{(time.time() - t0) / 60:.1f} min", flush=True)
    wall = time.time() - t0
    finish_parallel(out, args.preset, wall, args.jobs)
    print(f"soma bench accuracy: done in {wall / 60:.1f} min; wrote {out / 'table.md'}, {out / 'table.json'}")
    if failed:
        print(f"soma bench accuracy: error: object(s) failed: {', '.join(failed)}", file=sys.stderr)
        return 1
    return 0


def finish_parallel(out, preset: str, wall: float, jobs: int) -> None:
    """After the children: the whole run's wall time, job count and command line into
    OUT/bench.json and OUT/table.md (through the same locked writer the children use)."""
    import json
    from pathlib import Path

    from soma_ros.evaluation.accuracy import _command_line, _write, load_bench_config

    out = Path(out)
    if not (out / "bench.json").is_file() or not (out / "table.json").is_file():
        return
    meta = json.loads((out / "bench.json").read_text())
    meta.update({"wall_seconds": round(wall, 1), "jobs": jobs, "command": _command_line()})
    _write(out, json.loads((out / "table.json").read_text()), meta, load_bench_config(preset))


def register(subparsers) -> None:
    """Add ``accuracy`` to a ``soma bench`` sub-command parser set."""
    p = subparsers.add_parser("accuracy", help="accuracy table (Table 1 form) with baselines on reference-world data",
                              description=__doc__.splitlines()[0])
    add_arguments(p)
    p.set_defaults(bench_func=run)


def main(argv: Optional[Sequence[str]] = None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.bench_accuracy", description=__doc__.splitlines()[0])
    add_arguments(p)
    args = p.parse_args(argv)
    try:
        return run(args)
    except (FileNotFoundError, FileExistsError, ValueError, RuntimeError) as exc:
        print(f"bench accuracy: error: {exc}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
