"""`soma dataset check|inspect DATA`: what the trainer will see in a folder of recordings.

    soma dataset check DATA... [--config tiny] [--set KEY=VALUE] [--out DIR] [--frames N] [--no-sheets]
    soma dataset inspect DATA... [same options]

DATA: a folder of rosbag2 directories (with or without manifest.json), one bag, or
several bags (see :mod:`soma_ros.data.sources`). For every bag: its split, the cameras found
(topics, colour / depth encodings, rates, frame counts, the worst colour / depth offset
from the frame clock, the TF path of the camera frame), the joint names against the
URDF of the config's robot, and the masks' source (bag topics, PNG folder, derived).
A contact sheet of the masks (derived ones when the bag has none) for a few frames per
camera is written to DIR/masks_<bag>.png (object yellow, robot blue).

``check`` exits 1 and lists every problem, one line each; ``inspect`` prints the same
report and exits 0. Bags are only read.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from . import documented_parser


def register(subparsers) -> None:
    p = documented_parser(subparsers, "dataset", "check / inspect a folder of recordings before training", __doc__)
    p.add_argument("action", choices=["check", "inspect"])
    p.add_argument("data", nargs="+", metavar="DATA", help="a folder of bags, one bag, or several bags")
    p.add_argument("--config", default="tiny", help="train config whose robot, topics and mask settings apply")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override a config value")
    p.add_argument("--out", default="dataset_check", metavar="DIR", help="where the contact sheets go")
    p.add_argument("--frames", type=int, default=4, metavar="N", help="frames per camera in a contact sheet")
    p.add_argument("--no-sheets", action="store_true", help="no contact sheets (no mask derivation)")
    p.set_defaults(func=run)


def _mask_tile(rgb, obj, rob):
    import numpy as np

    t = rgb.astype(np.float32).copy()
    t[obj] = 0.45 * t[obj] + 0.55 * np.array([255, 220, 0], np.float32)
    t[rob] = 0.45 * t[rob] + 0.55 * np.array([0, 160, 255], np.float32)
    return t.clip(0, 255).astype(np.uint8)


def write_contact_sheet(ep, out: Path, frames: int) -> Path:
    """PNG: one row per frame, per camera its colour and its masks over the colour (object yellow, robot blue)."""
    import cv2
    import numpy as np

    T = ep.num_frames
    idx = sorted({int(round(i)) for i in np.linspace(0, T - 1, max(1, min(frames, T)))})
    rows = []
    for t in idx:
        tiles = []
        for c, name in enumerate(ep.camera_names):
            rgb = (ep.rgb[t, c].numpy() * 255).round().astype(np.uint8)
            m = _mask_tile(rgb, ep.object_mask[t, c].numpy(), ep.robot_mask[t, c].numpy())
            for tile in (rgb, m):
                tile = np.ascontiguousarray(tile[..., ::-1])
                cv2.putText(tile, f"{name} f{t}", (2, 10), cv2.FONT_HERSHEY_SIMPLEX, 0.3, (255, 255, 255), 1)
                tiles.append(tile)
                tiles.append(np.full((tile.shape[0], 2, 3), 40, np.uint8))
        rows.append(np.concatenate(tiles, axis=1))
        rows.append(np.full((2, rows[-1].shape[1], 3), 40, np.uint8))
    out.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(out), np.concatenate(rows, axis=0))
    return out


def run(args: argparse.Namespace) -> int:
    import torch

    from soma_ros.commands.train import parse_overrides
    from soma_ros.core.robot import RobotModel
    from soma_ros.data.bags import BagError
    from soma_ros.training.config import load_train_config
    from soma_ros.data.dataset import prepare_episode
    from soma_ros.data.sources import load_dataset, probe_bag

    torch.set_num_threads(1)
    cfg = load_train_config(args.config, parse_overrides(args.set))
    dc = cfg.data
    data = args.data[0] if len(args.data) == 1 else args.data
    refs = load_dataset(data, test_fraction=dc.split_test_fraction, seed=dc.split_seed)
    robot = RobotModel.from_config(cfg.robot, dtype=torch.float64)
    problems: list[str] = []
    out = Path(args.out)
    say = print
    say(f"soma dataset {args.action}: {len(refs)} bag(s) in {' '.join(args.data)}; robot {cfg.robot} "
        f"({len(robot.joint_names)} joints: {', '.join(robot.joint_names)})")
    usable = 0
    for r in refs:
        pr = probe_bag(r.bag, dc.topics, robot, dc.sync_tolerance_ms, dc.cameras)
        storage = ", ".join(sorted({p.suffix.lstrip(".") for p in Path(r.bag).iterdir() if p.suffix in (".db3", ".mcap")}))
        say(f"bag {r.name}  split={r.split}  storage={storage or '?'}  {sum(pr.counts.values())} messages")
        for cname, ct in sorted(pr.cameras.items()):
            n = pr.counts.get(ct.color, 0) if ct.color else 0
            rate = pr.rates_hz.get(ct.color, 0.0) if ct.color else 0.0
            enc = pr.encodings.get(ct.color, "?") if ct.color else "-"
            denc = pr.encodings.get(ct.depth, "?") if ct.depth else "-"
            say(f"  camera {cname} (/{ct.namespace}): colour {ct.color or '-'} [{enc}{', compressed' if ct.color_compressed else ''}] "
                f"{n} frames {rate:.1f} Hz; depth [{denc}]; info {ct.camera_info or '-'}; "
                f"sync worst {pr.sync_ms.get(cname, float('nan')):.1f} ms; TF: {pr.tf_paths.get(cname, '?')}; "
                f"masks: {'topics' if ct.object_mask else ('folder/derived' if dc.masks.source != 'bag' else 'MISSING')}")
        if pr.joint_names:
            extra = [j for j in pr.joint_names if j not in robot.urdf.joints]
            missing = [j for j in robot.joint_names + robot.gripper_joint_names if j not in pr.joint_names]
            say(f"  joints: {len(pr.joint_names)} in {dc.topics.joint_states}; robot joints missing: "
                f"{', '.join(missing) or 'none'}; not in the URDF: {', '.join(extra) or 'none'}")
        problems += pr.problems
        if not pr.ok:
            for p in pr.problems:
                say(f"  problem: {p}")
            continue
        if args.no_sheets:
            usable += 1
            continue
        try:
            ep = prepare_episode(r.bag, robot, dc, name=r.name)
        except (BagError, ValueError, FileNotFoundError) as exc:
            problems.append(str(exc))
            say(f"  problem: {exc}")
            continue
        usable += 1
        sheet = write_contact_sheet(ep, out / f"masks_{r.name.replace('/', '_')}.png", args.frames)
        cover = {c: float(ep.object_mask[:, i].float().mean()) * 100 for i, c in enumerate(ep.camera_names)}
        parts = [f"{c} {ep.mask_source.get(c, '?')} (object {cover[c]:.1f} % of pixels)" for c in ep.camera_names]
        say(f"  masks: {', '.join(parts)}; contact sheet {sheet}")
        for c, v in cover.items():
            if ep.mask_source.get(c) == "derived" and v == 0.0:
                problems.append(f"{r.name}: camera '{c}': the derived object mask is empty in every frame")
    say(f"{usable} of {len(refs)} bag(s) usable; {len(problems)} problem(s)")
    if problems:
        for p in problems:
            print(p, file=sys.stderr)
    return 1 if problems and args.action == "check" else 0
