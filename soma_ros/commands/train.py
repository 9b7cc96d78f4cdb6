"""`soma train`: fit the simulator offline from the rosbags of a dataset."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

DESCRIPTION = """\
Fit the learned simulator offline from episode bags: a folder of rosbag2
directories (with or without manifest.json; without one the split is
deterministic and written to RUN/split.json), one bag, or several. Masks a bag
lacks are derived from geometry (data.masks). A bad bag in a folder is listed
and skipped (--strict: fatal). Scene set-up from the first frame of a
training episode (or --scene), then training with the paper's two-stage
multi-resolution schedule (config/train/*.yaml).

RUN gets: checkpoint.pt (the simulator), scene/ (the scene bundle the nodes
load, with hierarchy.pt), train_state.pt (optimiser + schedule, for resuming),
log.csv, loss.png, train_config.yaml, summary.json, split.json, cache/masks/
(derived masks).

Run the same command again on the same RUN to resume after an interruption.
Multi-process / multi-GPU: torchrun --nproc_per_node N -m soma_ros.cli train ...
(DDP; gloo on CPU, nccl on GPU).
"""


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("train", help="fit the simulator offline from rosbags", description=DESCRIPTION,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", required=True, nargs="+", metavar="DATA",
                   help="a folder of bags (with or without manifest.json), one bag, or several bags")
    p.add_argument("--strict", action="store_true", help="a bad bag is fatal (default: it is listed and skipped)")
    p.add_argument("--config", default="tiny", help="train config: a name in config/train (tiny, paper) or a YAML path")
    p.add_argument("--out", required=True, help="run folder (created; an existing run there is resumed)")
    p.add_argument("--scene", default=None, help="use this scene bundle (from `soma reconstruct --bag`) instead of "
                                                 "setting one up from the first training episode")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override a config value, e.g. --set schedule.iters_per_epoch=10 (YAML value; repeatable)")
    p.add_argument("--max-iterations", type=int, default=None,
                   help="stop after this iteration (resumable partial run)")
    p.add_argument("--max-minutes", type=float, default=None, metavar="M",
                   help="stop once the training loop has run M minutes (iterations and validations, not the "
                        "scene set-up), validating and checkpointing the weights reached (resumable)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def parse_overrides(items: list[str]) -> dict:
    """['a.b=1', 'c=[1, 2]'] -> {'a': {'b': 1}, 'c': [1, 2]} (values parsed as YAML)."""
    import yaml

    out: dict = {}
    for item in items:
        if "=" not in item:
            raise ValueError(f"--set {item!r}: expected KEY=VALUE")
        key, value = item.split("=", 1)
        parts = [k for k in key.strip().split(".") if k]
        if not parts:
            raise ValueError(f"--set {item!r}: empty key")
        try:
            val = yaml.safe_load(value)
        except yaml.YAMLError:
            raise ValueError(f"--set {item!r}: the value is not valid YAML") from None
        d = out
        for k in parts[:-1]:
            d = d.setdefault(k, {})
            if not isinstance(d, dict):
                raise ValueError(f"--set {item!r}: '{k}' is set to a value and used as a section")
        d[parts[-1]] = val
    return out


def run(args: argparse.Namespace) -> int:
    from soma_ros.training.config import load_train_config
    from soma_ros.training.train import train

    cfg = load_train_config(args.config, parse_overrides(args.set))
    if args.quiet:
        cfg.run.progress = False
    if args.strict:
        cfg.data.strict = True
    data = Path(args.data[0]) if len(args.data) == 1 else [Path(p) for p in args.data]
    summary = train(cfg, data, Path(args.out), scene_dir=Path(args.scene) if args.scene else None,
                    max_iterations=args.max_iterations,
                    max_seconds=None if args.max_minutes is None else 60.0 * args.max_minutes)
    import os

    if int(os.environ.get("RANK", "0")) == 0:
        print(json.dumps(summary, indent=1))
    return 0
