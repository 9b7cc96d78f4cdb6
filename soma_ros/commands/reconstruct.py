"""`soma reconstruct`: the initial splat scene G_0 from a capture folder or from bags."""

from __future__ import annotations

import argparse
import json
from pathlib import Path


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "reconstruct", help="build the initial splat scene from bags or a multi-view capture",
        description="Build the initial Gaussian-splat scene G_0. From a multi-view capture folder "
                    "(images, masks, intrinsics, camera-to-world poses): fit on all views but the held-out "
                    "one and report the masked PSNR of the held-out view. From a reference-world or robot "
                    "episode bag: fuse masked depth of the first frame(s), fit photometrically, fit the table "
                    "plane and gravity, build the hierarchy, and write a scene bundle.")
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--capture", help="capture folder (img_i.png, mask_i.png, intr_list.npy, R_list.npy, t_list.npy)")
    src.add_argument("--bag", help="an episode bag directory (rosbag2)")
    p.add_argument("--holdout-view", type=int, default=None, help="capture view to hold out and evaluate")
    p.add_argument("--iters", type=int, default=None,
                   help="photometric optimisation iterations (capture: the preset's; bag: the config's "
                        "scene.photometric_iters)")
    p.add_argument("--quality", action="store_true",
                   help="with --capture: the GPU-sized fit preset (config/reconstruct/quality.yaml) instead of the "
                        "CPU-sized default (cpu.yaml)")
    p.add_argument("--fit-config", default=None, metavar="YAML",
                   help="with --capture: a fit settings file (keys of soma_ros.scene.splat_fit.FitConfig) instead of a preset")
    p.add_argument("--resolution-scale", type=float, default=1.0, help="image scale used for fitting")
    p.add_argument("--robot", default="panda", help="robot config (for a bag's wrist camera)")
    p.add_argument("--config", default=None, help="train config whose data/scene sections apply to a bag (tiny, paper, "
                                                  "a YAML path; default: built-in defaults)")
    p.add_argument("--ply", default=None, help="with --bag: take G_0 from this .ply (sim frame) instead of fusing depth")
    p.add_argument("--object", default="rope", help="object config (hierarchy thresholds), for bags")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import torch

    torch.manual_seed(args.seed)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    if args.capture:
        from soma_ros.scene.reconstruct import reconstruct_capture

        if args.quality and args.fit_config:
            raise ValueError("give --quality or --fit-config, not both")
        preset = args.fit_config or ("quality" if args.quality else "cpu")
        metrics = reconstruct_capture(Path(args.capture), out, holdout=args.holdout_view, iters=args.iters,
                                      scale=args.resolution_scale, progress=not args.quiet, preset=preset,
                                      overrides={"seed": int(args.seed)})
        print(json.dumps(metrics, indent=2))
        return 0
    from soma_ros.scene.reconstruct import reconstruct_bag

    if args.holdout_view is not None:
        raise ValueError("--holdout-view applies to --capture folders, not to --bag")
    if args.quality or args.fit_config:
        raise ValueError("--quality and --fit-config apply to --capture folders; a bag's fit follows its train "
                         "config's scene section")
    info = reconstruct_bag(Path(args.bag), out, robot=args.robot, object_name=args.object, iters=args.iters,
                           progress=not args.quiet, config=_train_config(args.config),
                           ply=Path(args.ply) if args.ply else None)
    print(json.dumps(info, indent=2))
    return 0


def _train_config(name):
    """The training config whose data and scene sections a bag's scene set-up follows."""
    from soma_ros.training.config import TrainConfig, load_train_config

    return load_train_config(name) if name else TrainConfig().validate()
