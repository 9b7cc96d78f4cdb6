"""Measure what each physical effect does: same seed, effect off vs on.

For one episode (object, preset, seed, index) this generates the baseline
and one episode per effect with the real generator, then reads back from the
bags (evaluation use of ``/world/object_points``, allowed here):

* ``final_mean_mm`` / ``final_max_mm``: per-vertex distance between the final
  object states (vertex order is fixed), mean and max, millimetres;
* ``centroid_mm``: distance between the final centroids;
* ``arm_max_diff_rad``: largest difference of the recorded arm joint
  positions over the whole episode (the commanded trajectory is the same;
  this is servo tracking under different loads);
* ``gripper_max_diff_m``: the same for the gripper joints (fingers stop where
  the object stops them, so this may differ).

Run: ``python -m soma_ros.world.effect_report --object rope --preset tiny``.
"""

from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path
from typing import Optional, Sequence

import numpy as np
from rosbags.highlevel import AnyReader

from .bag import OBJECT_POINTS_TOPIC, TYPESTORE
from .config import EFFECTS, WorldConfig, load_world_config
from .dataset import generate_episode

__all__ = ["read_states", "measure_effects"]


def read_states(bag_dir: Path) -> tuple[list[str], np.ndarray, np.ndarray]:
    """(joint names, joint positions [F, J], object points [F, N, 3]) of a recorded episode."""
    joints, points, names = [], [], []
    with AnyReader([Path(bag_dir)], default_typestore=TYPESTORE) as r:
        conns = [c for c in r.connections if c.topic in ("/joint_states", OBJECT_POINTS_TOPIC)]
        for c, _t, raw in r.messages(connections=conns):
            msg = r.deserialize(raw, c.msgtype)
            if c.topic == "/joint_states":
                joints.append(np.asarray(msg.position, float))
                names = list(msg.name)
            else:
                points.append(np.frombuffer(msg.data.tobytes(), "<f4").reshape(-1, 3).astype(float))
    return names, np.stack(joints), np.stack(points)


def measure_effects(
    cfg: WorldConfig,
    obj: str,
    preset: str = "tiny",
    seed: int = 0,
    index: int = 0,
    effects: Sequence[str] = EFFECTS,
    task: Optional[str] = None,
    frames: Optional[int] = None,
    work_dir: Optional[Path] = None,
) -> dict:
    """{"task", "frames", "baseline_seconds", "effects": {name: figures}} for one episode."""
    with tempfile.TemporaryDirectory(dir=work_dir) as tmp:
        tmp = Path(tmp)
        base_dir = tmp / "none"
        base_dir.mkdir()
        base = generate_episode(cfg, obj, preset, index, seed, [], base_dir, task=task, frames=frames)
        names, jb, pb = read_states(base_dir / base["bag"])
        rc = cfg.robot_config
        assert rc is not None
        arm = [names.index(j) for j in rc.arm_joints]
        grip = [names.index(j) for j in rc.gripper.joints]
        out = {"object": obj, "task": base["task"], "frames": base["frames"],
               "baseline_seconds": base["seconds_to_generate"], "effects": {}}
        for eff in effects:
            d = tmp / eff
            d.mkdir()
            e = generate_episode(cfg, obj, preset, index, seed, [eff], d, task=task, frames=frames)
            _, je, pe = read_states(d / e["bag"])
            dist = np.linalg.norm(pe[-1] - pb[-1], axis=1)
            out["effects"][eff] = {
                "final_mean_mm": round(float(dist.mean() * 1000), 2),
                "final_max_mm": round(float(dist.max() * 1000), 2),
                "centroid_mm": round(float(np.linalg.norm(pe[-1].mean(0) - pb[-1].mean(0)) * 1000), 2),
                "arm_max_diff_rad": float(np.max(np.abs(je[:, arm] - jb[:, arm]))),
                "gripper_max_diff_m": float(np.max(np.abs(je[:, grip] - jb[:, grip]))),
                "seconds": e["seconds_to_generate"],
            }
    return out


def main(argv: Optional[Sequence[str]] = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--object", required=True)
    ap.add_argument("--preset", default="tiny")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--index", type=int, default=0)
    ap.add_argument("--task", default=None)
    ap.add_argument("--frames", type=int, default=None)
    ap.add_argument("--effects", default=",".join(EFFECTS))
    ap.add_argument("--config", default="world/default")
    a = ap.parse_args(argv)
    cfg = load_world_config(a.config)
    res = measure_effects(cfg, a.object, a.preset, a.seed, a.index, a.effects.split(","), a.task, a.frames)
    print(json.dumps(res, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
