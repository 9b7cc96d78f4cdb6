"""Derived masks against the reference world's own: median IoU per object and camera.

    python -m benchmarks.bench_masks DATASET [DATASET ...] [--episodes N] [--config tiny] [--out FILE.json]

Each bag of each DATASET (reference-world folders, e.g. from `soma world`) is rewritten
without its mask topics and ``/world/object_points`` (``tools/rig_bags.py --strip-masks``)
into a temporary folder; the stripped bag goes through the trainer's ingestion
(:func:`soma_ros.data.dataset.prepare_episode`, masks derived from geometry:
:mod:`soma_ros.data.masks`) and its masks are compared, frame by frame at the recorded
resolution, with the original bag's mask topics. Printed per object and camera: the
median (and 10th percentile) IoU over all frames of all episodes, for the object and
for the robot, and the derivation time per frame; the machine and its load.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from soma_ros.core.machine import cpu_model

ROOT = Path(__file__).resolve().parents[1]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("datasets", nargs="+")
    ap.add_argument("--episodes", type=int, default=None, help="at most N bags per dataset")
    ap.add_argument("--config", default="tiny")
    ap.add_argument("--out", default=None)
    a = ap.parse_args(argv)
    import torch

    sys.path.insert(0, str(ROOT / "tools"))
    from rig_bags import RigForm, rewrite_bag

    from soma_ros.core.robot import RobotModel
    from soma_ros.data.bags import read_episode
    from soma_ros.training.config import load_train_config
    from soma_ros.data.dataset import prepare_episode
    from soma_ros.data.masks import mask_iou
    from soma_ros.data.sources import find_bags

    torch.set_num_threads(1)
    cfg = load_train_config(a.config)
    robot = RobotModel.from_config(cfg.robot, dtype=torch.float64)
    res: dict = {}
    load0 = os.getloadavg()
    with tempfile.TemporaryDirectory(prefix="bench_masks_") as tmp:
        for ds in a.datasets:
            bags = find_bags(Path(ds))[: a.episodes]
            for b in bags:
                man = json.loads((Path(ds) / "manifest.json").read_text()) if (Path(ds) / "manifest.json").is_file() else {}
                obj = man.get("object", Path(ds).name)
                stripped = rewrite_bag(b, Path(tmp) / f"{obj}_{b.name}", RigForm(strip_masks=True))
                truth = read_episode(b, require_masks=True)
                t0 = time.time()
                ep = prepare_episode(stripped, robot, cfg.data)
                dt = (time.time() - t0) / ep.num_frames
                assert set(ep.mask_source.values()) == {"derived"}, ep.mask_source
                for c in ep.camera_names:
                    ci = ep.camera_index(c)
                    s = truth.cameras[c]
                    om, rm = ep.object_mask[:, ci].numpy(), ep.robot_mask[:, ci].numpy()
                    r = res.setdefault(obj, {}).setdefault(c, {"object": [], "robot": [], "s_per_frame": []})
                    r["object"] += [mask_iou(om[t], s.object_mask[t]) for t in range(ep.num_frames)]
                    r["robot"] += [mask_iou(rm[t], s.robot_mask[t]) for t in range(ep.num_frames)]
                    r["s_per_frame"].append(dt)
    load1 = os.getloadavg()
    print(f"machine: {platform.node()} {cpu_model()}, {os.cpu_count()} CPUs, "
          f"load average {load0[0]:.1f} -> {load1[0]:.1f}")
    print(f"{'object':8s} {'camera':12s} {'frames':>6s} {'object IoU med (p10)':>22s} {'robot IoU med (p10)':>22s} {'s/frame':>8s}")
    summary = {}
    for obj, cams in res.items():
        for c, r in cams.items():
            o, rb = np.array(r["object"]), np.array(r["robot"])
            row = {"frames": len(o), "object_median": float(np.median(o)), "object_p10": float(np.percentile(o, 10)),
                   "robot_median": float(np.median(rb)), "robot_p10": float(np.percentile(rb, 10)),
                   "seconds_per_frame_all_cameras": float(np.mean(r["s_per_frame"]))}
            summary.setdefault(obj, {})[c] = row
            print(f"{obj:8s} {c:12s} {len(o):6d} {row['object_median']:14.3f} ({row['object_p10']:.3f}) "
                  f"{row['robot_median']:14.3f} ({row['robot_p10']:.3f}) {row['seconds_per_frame_all_cameras']:8.3f}")
    if a.out:
        Path(a.out).write_text(json.dumps({"load": [load0, load1], "results": summary}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
