"""`soma world`: generate reference-world episodes (MuJoCo) recorded as rosbags."""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

DESCRIPTION = """\
Generate episodes of an arm with a parallel gripper manipulating a deformable
object on a table, simulated and rendered with MuJoCo (CPU, offscreen), and
record each episode as a rosbag2 directory exactly like a real rig with three
RealSense-style cameras would.

Objects: rope, cloth, doll (a soft volumetric plush figure).
Tasks:   lift (grasp-and-lift), drag (grasp and drag on the table),
         fold (cloth only: carry a corner over to the opposite corner).
         Tasks take turns over the episodes (seeded start) unless --task is given.
Robot:   the Panda URDF by default (config/world/robot_panda.yaml), loaded
         unchanged; choose another robot YAML in the world config.

Every episode i of seed S is reproducible: frame count, object
placement/shape and motion sizes come from SeedSequence([S, i]). Effects
change nothing in the robot's motion: same seed, same joint trajectory.

Output (DIR):
  DIR/manifest.json         object, preset, seed, effects, storage, split_ratio,
                            episodes [{name, bag, split (train|test), task,
                            frames, seconds_to_generate}]
  DIR/<object>_NNN/         one rosbag2 directory per episode
  DIR/<object>_NNN.meta.json  EVALUATION-ONLY sidecar: effects and magnitudes,
                            object physical parameters, table height, task,
                            seed, true wrist-camera poses
  DIR/<object>_NNN.contact.png  contact sheet (RGB, depth, masks per camera)

Topics in each bag (one header stamp per frame, 30 FPS):
  /joint_states                                  sensor_msgs/JointState (URDF names,
                                                 position + velocity; effort: the arm's
                                                 external torques (N m) and the gripper's
                                                 force (N), robot YAML `effort`)
  /<cam>/color/image_raw                         sensor_msgs/Image rgb8
  /<cam>/color/camera_info                       sensor_msgs/CameraInfo plumb_bob
  /<cam>/aligned_depth_to_color/image_raw        sensor_msgs/Image 16UC1 (mm, 0 = none)
  /<cam>/aligned_depth_to_color/camera_info      sensor_msgs/CameraInfo (the colour one's)
  /<cam>/object_mask, /<cam>/robot_mask          sensor_msgs/Image mono8 (255 = yes)
  /tf_static                                     tf2_msgs/TFMessage (world -> base link,
                                                 world -> fixed cameras, hand -> wrist camera)
  /tf                                            tf2_msgs/TFMessage (every URDF joint from the
                                                 joint state, as robot_state_publisher)
  /robot_description                             std_msgs/String URDF (latched)
  /world/object_points                           sensor_msgs/PointCloud2 x,y,z in world:
                                                 ground truth, EVALUATION-ONLY, training
                                                 code must never read it
  with <cam> in cam_wrist, cam_front, cam_side.

Effects (off by default; magnitudes in config/world/effects.yaml; recorded
only in the sidecars and the manifest's effect list, never in the bag):
  wind            steady wind (pressure drag of the object's elements against it)
  air_drag        the same drag in still air, of an exaggerated density
  table_friction  slippery table
  slip            the grasp slips while carrying
  stiff           10x Young's modulus
  heavy           3x object mass

Rendering runs on the CPU offscreen: Mesa EGL (MUJOCO_GL=egl, the default)
or OSMesa (MUJOCO_GL=osmesa).

Presets (config/world/default.yaml):
  tiny    CI-sized: 3 episodes of 40 frames at 160x120
  paper   35 episodes of 100-150 frames at 640x480, 7:3 train/test split
          (about 6 MB per frame on disk: ~0.9 GB per 143-frame episode)
"""

EPILOG = """\
examples:
  soma world --object rope --preset tiny --out data/rope_tiny
  soma world --object cloth --preset paper --seed 3 --out data/cloth
  soma world --object doll --preset tiny --effects wind,slip --out data/doll_wind
  soma world --object cloth --preset tiny --task fold --storage mcap --out data/fold
"""


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "world",
        help="generate reference-world episodes (MuJoCo) recorded as rosbags",
        description=DESCRIPTION,
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--object", required=True, choices=["rope", "cloth", "doll"], help="deformable object")
    p.add_argument("--preset", default="tiny", help="dataset size preset: tiny | paper (default: tiny)")
    p.add_argument("--out", required=True, metavar="DIR", help="output directory (created if missing)")
    p.add_argument("--episodes", type=int, default=None, metavar="N", help="number of episodes (default: the preset's)")
    p.add_argument("--seed", type=int, default=0, metavar="S", help="random seed of the dataset (default: 0)")
    p.add_argument(
        "--effects",
        default="",
        metavar="LIST",
        help="comma-separated physical effects to switch on: wind,air_drag,table_friction,slip,stiff,heavy "
        "(default: none)",
    )
    p.add_argument("--task", default=None, choices=["lift", "drag", "fold", "drop"], help="force one task for every episode")
    p.add_argument("--frames", type=int, default=None, metavar="N", help="override the frames per episode (>= 8)")
    p.add_argument("--storage", default="sqlite3", choices=["sqlite3", "mcap"], help="rosbag2 storage (default: sqlite3)")
    p.add_argument("--config", default="world/default", metavar="YAML",
                   help="world config (default: config/world/default.yaml)")
    p.add_argument("--overwrite", action="store_true", help="replace this dataset's existing outputs in DIR")
    p.add_argument("--workers", type=int, default=1, metavar="N",
                   help="episodes generated at once, one process each (default: 1); the bags do not depend on it")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    try:
        from ..world import generate_dataset, load_world_config, parse_effects
    except Exception as exc:  # MuJoCo or its GL backend cannot load: say so in one line
        backend = os.environ.get("MUJOCO_GL", "egl")
        raise RuntimeError(
            f"cannot load MuJoCo for offscreen rendering (MUJOCO_GL={backend}): {exc.__class__.__name__}: {exc}"
        ) from None

    cfg = load_world_config(args.config)
    effects = parse_effects(args.effects)
    t0 = time.perf_counter()
    try:
        manifest = generate_dataset(
            cfg,
            args.object,
            args.preset,
            args.out,
            episodes=args.episodes,
            seed=args.seed,
            effects=effects,
            storage=args.storage,
            task=args.task,
            frames=args.frames,
            overwrite=args.overwrite,
            progress=not args.quiet,
            workers=args.workers,
        )
    except FileExistsError as exc:  # reported by the CLI as a one-line error
        raise RuntimeError(str(exc)) from None
    eps = manifest["episodes"]
    secs = [e["seconds_to_generate"] for e in eps]
    summary = {
        "out": str(args.out),
        "object": args.object,
        "preset": args.preset,
        "episodes": len(eps),
        "train": sum(e["split"] == "train" for e in eps),
        "test": sum(e["split"] == "test" for e in eps),
        "effects": effects,
        "seconds_per_episode_mean": round(sum(secs) / len(secs), 3),
        "seconds_total": round(time.perf_counter() - t0, 3),
    }
    print(json.dumps(summary), file=sys.stdout)
    return 0
