"""`soma scene align`: a user's splat scan registered to a rig by Sim(3), written as a scene bundle."""

from __future__ import annotations

import argparse
import json
from pathlib import Path


def register(s: argparse._SubParsersAction) -> None:
    a = s.add_parser(
        "align", help="register a .ply/.splat scan to a capture or a bag by Sim(3) and write a scene bundle",
        description="Register a user's Gaussian-splat scan (.ply or .splat, any frame and scale) to the rig's "
                    "frame by a similarity transform: coarse start from the rig's object points (a capture's "
                    "pcd.ply, masked depth or mask hull; a bag's fused masked depth), ICP with scale, a short "
                    "photometric refinement against the rig's views. Writes a scene bundle (splats.ply, "
                    "scene.json, hierarchy.pt) for `soma train --scene` and soma_sim_node, and align.json with "
                    "the transform, the residual in mm and the masked PSNR of the aligned scan in every view.")
    src = a.add_mutually_exclusive_group(required=True)
    src.add_argument("--capture", help="capture folder (img_i.png, mask_i.png, intr_list.npy, R_list.npy, t_list.npy)")
    src.add_argument("--bag", help="an episode bag directory (rosbag2)")
    a.add_argument("--file", required=True, help="the scan: .ply (3DGS or plain points) or .splat")
    a.add_argument("--out", required=True, help="output scene bundle folder")
    a.add_argument("--object", default="rope", help="object config (mass, hierarchy thresholds)")
    a.add_argument("--robot", default="panda", help="robot config recorded in the bundle (bag: its wrist camera)")
    a.add_argument("--config", default=None, help="with --bag: train config whose data/scene sections apply")
    a.add_argument("--photometric-iters", type=int, default=None, help="iterations of the photometric refinement "
                                                                       "(default 150; 0 = geometry only)")
    a.add_argument("--trim", type=float, default=None, help="ICP inlier distance in metres (default 0.01)")
    a.add_argument("--holdout-view", type=int, default=None,
                   help="with --capture: fit the photometric stage to the other views and score this one held out")
    a.add_argument("--seed", type=int, default=None, help="seed of the photometric stage's view order (default 0)")
    a.add_argument("--dt", type=float, default=1 / 30, help="with --capture: frame interval stored in the bundle (s)")
    a.add_argument("--quiet", action="store_true", help="no progress bar")
    a.set_defaults(func=run_align)


def run_align(args: argparse.Namespace) -> int:
    from soma_ros.scene.scene_align import AlignConfig
    from soma_ros.scene.scene_align import align_to_bag, align_to_capture

    cfg = AlignConfig()
    if args.photometric_iters is not None:
        cfg.photometric_iters = int(args.photometric_iters)
    if args.trim is not None:
        cfg.trim_distance = float(args.trim)
    if args.seed is not None:
        cfg.seed = int(args.seed)
    cfg.validate()
    if not Path(args.file).is_file():
        raise FileNotFoundError(f"scan file not found: {args.file}")
    if args.capture:
        report = align_to_capture(Path(args.file), Path(args.capture), Path(args.out), cfg, object_name=args.object,
                                  robot=args.robot, dt=args.dt, progress=not args.quiet,
                                  holdout_view=args.holdout_view)
    else:
        if args.holdout_view is not None:
            raise ValueError("scene align: --holdout-view applies to --capture only")
        report = align_to_bag(Path(args.file), Path(args.bag), Path(args.out), cfg, object_name=args.object,
                              robot=args.robot, config=_train_config(args.config), progress=not args.quiet)
    print(json.dumps(report, indent=2))
    return 0


def _train_config(name):
    """The training config whose data and scene sections a bag's scene set-up follows."""
    from soma_ros.training.config import TrainConfig, load_train_config

    return load_train_config(name) if name else TrainConfig().validate()
