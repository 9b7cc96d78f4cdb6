"""Accuracy benchmark: the form of the paper's Table 1 on reference-world data, with baselines.

    soma bench accuracy --preset tiny --out runs/accuracy              # rope, cloth, doll
    soma bench accuracy --preset tiny --objects rope --out runs/acc    # one object
    python -m benchmarks.bench_accuracy --preset tiny --out runs/acc   # same, without the soma CLI

For each object: generate (or reuse) a reference-world dataset, train every
learned variant with ``soma train`` (full, state_only, img_only, no_mrt), fit
the spring-mass baseline, evaluate all of them and ``static`` on the training
(resimulation) and held-out (generalization) episodes, and write OUT/table.md,
OUT/table.json ({object: {variant: {split: {metric: value}}}}) and
OUT/bench.json. Presets: config/eval/<preset>.yaml (tiny: 2-core CPU, under
an hour per object; paper: the paper's scale, for a GPU). See
:mod:`trainer.bench_accuracy`.
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
                   help="comma-separated variants (default: full,static,state_only,spring_mass,img_only,no_mrt)")
    p.add_argument("--out", required=True, metavar="DIR", help="output folder (data/, runs/, eval/, table.md, table.json)")
    p.add_argument("--episodes", type=int, default=None, metavar="N", help="episodes per object (default: the preset's)")
    p.add_argument("--seed", type=int, default=None, metavar="S", help="reference-world seed (default: the preset's)")
    p.add_argument("--fresh", action="store_true", help="start over (delete OUT/data, OUT/runs, OUT/eval)")
    p.add_argument("--quiet", action="store_true", help="no progress bars")


def run(args: argparse.Namespace) -> int:
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    os.environ.setdefault("MUJOCO_GL", "egl")
    import dataclasses
    from pathlib import Path

    import torch

    torch.set_num_threads(int(os.environ.get("OMP_NUM_THREADS", "1") or 1))
    from trainer.bench_accuracy import load_bench_config, run_bench

    bench = load_bench_config(args.preset)
    if args.variants:
        bench = dataclasses.replace(bench, variants=[v.strip() for v in args.variants.split(",") if v.strip()])
    if args.episodes is not None or args.seed is not None:
        w = dataclasses.replace(bench.world, episodes=args.episodes if args.episodes is not None else bench.world.episodes,
                                seed=args.seed if args.seed is not None else bench.world.seed)
        bench = dataclasses.replace(bench, world=w)
    bench.validate()
    objects = [o.strip() for o in args.objects.split(",") if o.strip()] if args.objects else None
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
