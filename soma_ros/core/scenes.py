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
