"""Procedural splat scenes: handy defaults for demos, tests and first runs."""

from __future__ import annotations

import math

import torch

from .splats import Splats


def synthetic_rope(
    n: int = 13000,
    length: float = 0.4,
    radius: float = 0.008,
    center: tuple[float, float, float] = (0.5, 0.0, 0.01),
    seed: int = 0,
) -> Splats:
    """A rope-shaped splat scene: n splats filling a gently curved tube on z = 0 (metres).

    The tube runs along x with its centre line at `center`, bending by a
    quarter of its radius of curvature; colours vary along its length so that
    motion is visible in renders.
    """
    if n <= 0:
        raise ValueError(f"synthetic_rope needs n > 0, got {n}")
    g = torch.Generator().manual_seed(seed)
    u = torch.rand(n, generator=g)
    theta = torch.rand(n, generator=g) * 2 * math.pi
    r = radius * torch.sqrt(torch.rand(n, generator=g))
    x = (u - 0.5) * length
    y = 0.03 * torch.sin(u * math.pi)
    pts = torch.stack([x, y + r * torch.cos(theta), r * torch.sin(theta) + radius], dim=-1)
    pts = pts + torch.tensor(center)
    colors = torch.stack([0.8 - 0.5 * u, 0.3 + 0.4 * u, 0.2 + 0.1 * torch.rand(n, generator=g)], dim=-1)
    return Splats.from_points(pts, colors, scale=radius * 0.35, opacity=0.9, total_mass=0.05)


def synthetic_bundle(n: int = 13000, seed: int = 0, width: int = 320, height: int = 240,
                     table_height: float = 0.75):
    """A SceneBundle with a synthetic rope on a table in front of a Panda.

    World frame z-up, table top at `table_height`, the robot base on the table
    at the origin, one fixed camera looking at the rope and one on the Panda's
    hand (``panda_hand``). For tests, demos and first runs without data.
    """
    import numpy as np

    from .cameras import look_at
    from .scene_bundle import CameraSpec, SceneBundle

    rope = synthetic_rope(n, center=(0.5, 0.0, table_height), seed=seed)
    f = 0.9 * width
    K = np.array([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1.0]])
    front = look_at((1.1, 0.05, table_height + 0.55), (0.5, 0.0, table_height)).numpy()
    mount = np.eye(4)
    mount[:3, 3] = (0.05, 0.0, 0.04)  # optical axis along the hand's approach (+z)
    base = {"scale": 1.0, "rotation": np.eye(3).tolist(), "translation": [0.0, 0.0, table_height]}
    return SceneBundle(
        splats=rope, gravity=np.array([0.0, 0.0, -9.81]), table_normal=np.array([0.0, 0.0, 1.0]),
        table_offset=-table_height, dt=1.0 / 30.0, sim_frame="world", object_name="rope", robot_config="panda",
        base_to_sim=base,
        cameras=[CameraSpec("cam_front", width, height, K, cam_to_sim=front),
                 CameraSpec("cam_wrist", width, height, K, mount_link="panda_hand", link_to_cam=mount)],
    )


def write_untrained_run(out_dir, n: int = 13000, model: str = "cpu", seed: int = 0, width: int = 320,
                        height: int = 240):
    """OUT/checkpoint.pt (random weights, `model` config) + OUT/scene (synthetic_bundle).

    The random model is a real simulator: at rest it stays put, and the robot
    force term moves whatever the gripper touches. Returns (checkpoint, scene dir).
    """
    from pathlib import Path

    from .checkpoint import save_checkpoint
    from .config import load_model_config
    from .simulator import Simulator

    out = Path(out_dir)
    torch.manual_seed(seed)
    bundle = synthetic_bundle(n, seed=seed, width=width, height=height)
    sim = Simulator(load_model_config(model, object="rope"))
    with torch.no_grad():
        sim.init_state(bundle.splats, bundle.scene_context())
    ckpt = save_checkpoint(out / "checkpoint.pt", sim, extra={"note": "untrained (random weights)"})
    scene = bundle.save(out / "scene")
    return ckpt, scene
