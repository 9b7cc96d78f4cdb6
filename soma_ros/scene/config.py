"""Scene set-up settings: the ``scene:`` section of a training config (how G_0, the table plane
and each episode's initial state are made from an episode's first frames)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Optional

from soma_ros.core.config import ConfigError

__all__ = ["SceneConfig"]


@dataclass
class SceneConfig:
    """Scene set-up from the first frame(s) of an episode (:mod:`soma_ros.scene.scene_setup`).

    ``num_splats``: target number of splats of G_0 (voxel size found by bisection
    on the fused object points; the paper uses 13,000). ``frames``: frames whose
    masked depth is fused. ``photometric_*``: the photometric fit of
    :func:`soma_ros.scene.splat_fit.fit_splats` on those frames' views (L1 + D-SSIM, alpha and
    depth terms), positions and splat count fixed.
    ``table_*``: RANSAC on non-object, non-robot depth within ``table_radius`` m
    of the object. ``align_*``: per-episode initial state = G_0 moved onto the
    episode's frame-0 object points, rigid ICP then an as-rigid-as-possible
    refinement of the fine clusters (``align_nonrigid_iters: 0`` = rigid only).
    """

    source_episode: Optional[str] = None
    frames: list[int] = field(default_factory=lambda: [0])  # frames whose masked depth is fused (and fitted to)
    num_splats: int = 2000
    splat_scale_factor: float = 0.6
    opacity: float = 0.9
    erode_px: int = 0
    photometric_iters: int = 60  # renderer-based refinement of colours / opacities / scales on ``frames`` (0 = off)
    photometric_lr_color: float = 0.02  # the fit's Adam rate for colours
    photometric_lr_scale: float = 0.01  # ... for log-scales (0: the splats keep their initial, round shape)
    photometric_lr_opacity: float = 0.02  # ... for opacity logits
    photometric_aniso_reg: float = 0.0  # weight of mean relu(log(max / min scale) - log(photometric_max_aniso))
    #   in the fit; 1 with photometric_max_aniso 1 keeps the splats nearly round, only their size fitted
    #   (docs/design_decisions.md "Scene set-up")
    photometric_max_aniso: float = 10.0  # axis ratio a splat may reach before photometric_aniso_reg costs (>= 1)
    table_radius: float = 0.4
    table_threshold: float = 0.004
    table_iters: int = 400
    g: float = 9.81
    align_icp_iters: int = 30
    align_nonrigid_iters: int = 150
    align_nonrigid_lr: float = 0.003
    align_rigidity: float = 3.0
    align_max_distance: float = 0.05

    def validate(self, where: str = "scene") -> None:
        if self.num_splats < 10:
            raise ConfigError(f"{where}.num_splats: must be >= 10, got {self.num_splats}")
        if not self.frames or any(f < 0 for f in self.frames):
            raise ConfigError(f"{where}.frames: a non-empty list of frame indices >= 0, got {self.frames}")
        for name in ("splat_scale_factor", "table_radius", "table_threshold", "g", "align_max_distance"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ConfigError(f"{where}.{name}: must be finite and > 0, got {v}")
        if not 0 < self.opacity < 1:
            raise ConfigError(f"{where}.opacity: must lie in (0, 1), got {self.opacity}")
        if not (math.isfinite(self.photometric_aniso_reg) and self.photometric_aniso_reg >= 0):
            raise ConfigError(f"{where}.photometric_aniso_reg: must be finite and >= 0, got {self.photometric_aniso_reg}")
        if not (math.isfinite(self.photometric_max_aniso) and self.photometric_max_aniso >= 1):
            raise ConfigError(f"{where}.photometric_max_aniso: must be finite and >= 1, got {self.photometric_max_aniso}")
        if min(self.photometric_iters, self.align_icp_iters, self.align_nonrigid_iters, self.erode_px) < 0:
            raise ConfigError(f"{where}: iteration counts and erode_px must be >= 0")
