"""`soma eval`: score a trained model by open-loop rollouts on a dataset split.

    soma eval --checkpoint RUN --data DATASET --split test [--out DIR] [--video]

``--checkpoint``: a ``soma train`` run folder (``checkpoint.pt``, ``scene/``,
``train_config.yaml``), a ``checkpoint.pt`` inside one, a fitted spring-mass
model (``spring_mass.pt`` or its folder, as ``soma bench accuracy`` writes
them), or ``static`` (splats that never move; needs ``--run`` for the scene).
``--prior-only``: the checkpoint's simulator with the network's contribution
switched off (the ``prior_only`` baseline: its physical terms alone).
``--run`` names the run whose scene and data/alignment settings define the
initial states (default: the checkpoint's folder). Writes DIR/metrics.json,
DIR/table.md, DIR/sheets/*.png (and DIR/videos/*.mp4); see
:mod:`soma_ros.evaluation.evaluate` for the protocol.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from . import documented_parser


def register(subparsers) -> None:
    p = documented_parser(subparsers, "eval", "evaluate a checkpoint on a dataset (open-loop rollouts)", __doc__)
    p.add_argument("--checkpoint", required=True, metavar="CKPT",
                   help="run folder, checkpoint.pt, spring_mass.pt (or its folder), or 'static'")
    p.add_argument("--data", required=True, nargs="+", metavar="DATA",
                   help="a folder of bags (with or without manifest.json), one bag, or several bags")
    p.add_argument("--strict", action="store_true", help="a bad bag is fatal (default: it is listed and skipped)")
    p.add_argument("--split", default="test", choices=["train", "test"], help="episodes to score (default: test)")
    p.add_argument("--out", default=None, metavar="DIR", help="output folder (default: RUN/eval_<split>)")
    p.add_argument("--run", default=None, metavar="RUN",
                   help="run folder giving the scene and the data settings (default: the checkpoint's folder)")
    p.add_argument("--scene", default=None, metavar="DIR", help="scene bundle to start from (default: RUN/scene)")
    p.add_argument("--prior-only", action="store_true",
                   help="switch the simulator's network off: the prior_only baseline (its physical terms alone)")
    p.add_argument("--name", default=None, help="variant name in the report (default: from the checkpoint)")
    p.add_argument("--max-episodes", type=int, default=None, metavar="N", help="score only the first N episodes")
    p.add_argument("--frame-stride", type=int, default=1, metavar="K", help="score every K-th frame (default: 1)")
    p.add_argument("--sheet-frames", type=int, default=5, metavar="N", help="rows per contact sheet (default: 5)")
    p.add_argument("--no-sheets", action="store_true", help="no contact sheets")
    p.add_argument("--video", action="store_true", help="also write an mp4 per episode")
    p.add_argument("--no-lpips", action="store_true", help="skip LPIPS (faster)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def _run_dir(ckpt: str, run: str | None) -> Path:
    if run is not None:
        return Path(run)
    p = Path(ckpt)
    if ckpt == "static":
        raise ValueError("--checkpoint static needs --run RUN (the run whose scene it starts from)")
    if not p.exists():
        raise FileNotFoundError(f"checkpoint not found: {p}")
    return p if p.is_dir() else p.parent


def run(args: argparse.Namespace) -> int:
    import torch

    torch.set_num_threads(1)
    from soma_ros.evaluation.baselines import StaticModel, load_model
    from soma_ros.evaluation.evaluate import EvalConfig, EvalContext, evaluate_models, format_metric
    from soma_ros.core.scoring import METRICS, EvalMetricsConfig

    if args.max_episodes is not None and args.max_episodes < 1:
        raise ValueError("--max-episodes must be >= 1")
    if args.frame_stride < 1:
        raise ValueError("--frame-stride must be >= 1")
    run_dir = _run_dir(args.checkpoint, args.run)
    t0 = time.time()
    if args.prior_only and args.checkpoint == "static":
        raise ValueError("--prior-only needs a simulator checkpoint, not 'static'")
    model = StaticModel() if args.checkpoint == "static" else load_model(args.checkpoint, network=not args.prior_only)
    name = args.name or ("static" if args.checkpoint == "static" else "prior_only" if args.prior_only
                         else Path(args.checkpoint).resolve().name.replace(".pt", ""))
    data = args.data[0] if len(args.data) == 1 else args.data
    ctx = EvalContext.from_run(run_dir, data, args.scene, strict=True if args.strict else None)
    for line in ctx.skipped:
        print(f"soma eval: {line}", file=sys.stderr)
    out = Path(args.out) if args.out else run_dir / f"eval_{args.split}"
    cfg = EvalConfig(metrics=EvalMetricsConfig(with_lpips=not args.no_lpips), frame_stride=args.frame_stride,
                     max_episodes=args.max_episodes, contact_sheets=not args.no_sheets, sheet_frames=args.sheet_frames,
                     video=args.video, progress=not args.quiet)
    res = evaluate_models({name: model}, ctx, args.split, {name: out}, cfg, log=lambda s: None)[name]
    mean = res["mean"]
    print(f"soma eval: {name} on {mean['episodes']} {args.split} episode(s) of {' '.join(args.data)} "
          f"({time.time() - t0:.0f} s)")
    print("  " + "  ".join(f"{m}={format_metric(m, mean.get(m))}" for m in METRICS))
    for n in res.get("notes", []):
        print(f"  note: {n}", file=sys.stderr)
    print(f"  wrote {out / 'metrics.json'}, {out / 'table.md'}" + (f", {out / 'sheets'}/" if not args.no_sheets else "")
          + (f", {out / 'videos'}/" if args.video else ""))
    return 0
