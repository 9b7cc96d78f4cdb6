"""`soma discrepancy`: find where the model and measured data disagree, name the missing effect,
add it to the model and show the gap shrink (issue #8).

    soma discrepancy --checkpoint RUN/checkpoint.pt --data MEASURED --out DIR [--config default|fast|YAML] [--jobs N]

``--checkpoint``: a ``soma train`` run folder or the ``checkpoint.pt`` in one (its ``scene/`` and
``train_config.yaml`` define the initial states). ``--data``: the measured dataset (manifest.json
+ bags); its ``test`` split is held out, the other episodes are used to fit the candidates.
``--reference``: episodes recorded under the conditions the model was trained in, which it was
not trained on (default: the checkpoint's training dataset, its episodes outside the train split;
``none``: no own-error control). Every candidate is calibrated there first, so a term that only
fixes the model's own error is not named. Writes DIR/report.md, DIR/report.json (named_effect, ranking, gap_before, gap_after), plots, and
DIR/model/ (the model with the named effect added: a run folder ``soma eval`` accepts).
See :mod:`soma_ros.discrepancy.workflow` for the method.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

from . import documented_parser


def register(subparsers) -> None:
    p = documented_parser(subparsers, "discrepancy", "find and name effects missing from the model", __doc__)
    p.add_argument("--checkpoint", required=True, metavar="CKPT", help="run folder or its checkpoint.pt")
    p.add_argument("--data", required=True, metavar="MEASURED", help="measured dataset folder (manifest.json + bags)")
    p.add_argument("--out", required=True, metavar="DIR", help="output folder")
    p.add_argument("--config", default="default", metavar="NAME|YAML",
                   help="config/discrepancy/<name>.yaml or a YAML path (default: default)")
    p.add_argument("--scene", default=None, metavar="DIR", help="scene bundle (default: the run's scene/)")
    p.add_argument("--candidates", default=None, metavar="LIST", help="comma-separated effect names (default: the config's)")
    p.add_argument("--reference", default=None, metavar="DATA",
                   help="dataset of the model's own conditions for the own-error control (default: the checkpoint's "
                        "training dataset outside its train split; 'none': off)")
    p.add_argument("--fit-iters", type=int, default=None, metavar="N", help="Adam steps per candidate")
    p.add_argument("--jobs", type=int, default=None, metavar="N",
                   help="fit the candidates in N worker processes (CPU models; default: the config's, 1); "
                        "the results do not depend on it")
    p.add_argument("--feature-only", action="store_true",
                   help="add candidates as network features only (default: direct effects, their force is also "
                        "integrated explicitly on top of the learned dynamics)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    import torch

    torch.set_num_threads(int(os.environ.get("OMP_NUM_THREADS", "1") or 1))
    from soma_ros.discrepancy.workflow import load_discrepancy_config, run_discrepancy

    over = {}
    if args.candidates:
        over["candidates"] = [c.strip() for c in args.candidates.split(",") if c.strip()]
    if args.fit_iters is not None:
        over["fit_iters"] = args.fit_iters
    if args.reference is not None:
        over["reference_data"] = args.reference
    if args.feature_only:
        over["direct"] = False
    if args.jobs is not None:
        over["jobs"] = args.jobs
    try:
        cfg = load_discrepancy_config(args.config, over)
        rep = run_discrepancy(Path(args.checkpoint), Path(args.data), Path(args.out), cfg,
                              None if args.scene is None else Path(args.scene), log=lambda s: print(s, flush=True))
    except (FileNotFoundError, ValueError) as exc:
        print(f"soma discrepancy: error: {exc}", file=sys.stderr)
        return 2
    gb, ga = rep["gap_before"], rep["gap_after"]
    print(f"named effect: {rep['named_effect']}")
    for m in ("rmse", "chamfer", "points"):
        if gb.get(m) is not None and ga.get(m) is not None:
            print(f"  {m}: {gb[m]:.5f} -> {ga[m]:.5f}")
    return 0
