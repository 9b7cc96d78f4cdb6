"""The MuJoCo reference world: episodes recorded as rosbag2 directories like a real rig.

It stands in for reality: a physics engine and renderer nobody tunes toward the
learned model. An arm (the Panda URDF by default, chosen in config) with a
parallel gripper grasps and lifts, drags or folds a deformable object (rope,
cloth, doll) on a table; three cameras (``cam_wrist``, ``cam_front``,
``cam_side``) record RGB, metric depth and object/robot masks at 30 FPS.

Public API::

    from soma_ros.world import load_world_config, generate_dataset
    cfg = load_world_config()                      # config/world/default.yaml
    manifest = generate_dataset(cfg, "rope", "tiny", "out/rope_tiny", seed=0,
                                effects=["wind"])  # -> manifest dict

``/world/object_points`` in the bags and the ``<episode>.meta.json`` sidecars
are EVALUATION-ONLY: training code must never read them.
"""

from __future__ import annotations

import os

# Offscreen CPU rendering (Mesa EGL) unless the caller chose a backend; must precede `import mujoco`.
os.environ.setdefault("MUJOCO_GL", "egl")

from .bag import OBJECT_POINTS_TOPIC, STORAGES, topics_for  # noqa: E402
from .config import (  # noqa: E402
    EFFECTS,
    OBJECTS,
    TASKS,
    EffectsConfig,
    RobotConfig,
    WorldConfig,
    load_effects_config,
    load_robot_config,
    load_world_config,
)
from .dataset import episode_name, generate_dataset, generate_episode, split_indices  # noqa: E402
from .effects import parse_effects  # noqa: E402
from .render import intrinsics  # noqa: E402
from .scene import CAMERA_NAMES, optical_frame_id  # noqa: E402

__all__ = [
    "CAMERA_NAMES",
    "EFFECTS",
    "OBJECTS",
    "TASKS",
    "STORAGES",
    "OBJECT_POINTS_TOPIC",
    "EffectsConfig",
    "RobotConfig",
    "WorldConfig",
    "episode_name",
    "generate_dataset",
    "generate_episode",
    "intrinsics",
    "load_effects_config",
    "load_robot_config",
    "load_world_config",
    "optical_frame_id",
    "parse_effects",
    "split_indices",
    "topics_for",
]
