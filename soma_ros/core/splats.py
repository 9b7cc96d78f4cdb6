"""The Gaussian-splat scene type.

A :class:`Splats` holds N anisotropic 3D Gaussians in one frame (the
simulation / reconstruction frame, metres):

==============  ===========  ==============================================
field           shape        meaning
==============  ===========  ==============================================
means           [N, 3]       centres, metres
quats           [N, 4]       unit rotation, (w, x, y, z)
scales          [N, 3]       standard deviations along the local axes, metres
opacities       [N]          in [0, 1] (not logits)
sh_dc           [N, 3]       degree-0 spherical-harmonic colour coefficients
sh_rest         [N, K, 3]    higher SH bands (K = 0, 3, 8 or 15), may be empty
mass            [N]          kg (uniform total mass by default)
attrs           [N, A]       learned per-splat physical attributes (A >= 0)
==============  ===========  ==============================================

Colour of a splat seen from any direction at SH degree 0 is
``clamp(0.5 + SH_C0 * sh_dc, 0, 1)``; this is the convention of the
standard 3DGS ``.ply`` files.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Optional

import torch

from .geometry import covariance_from_scale_rot, quat_normalize

SH_C0 = 0.28209479177387814

__all__ = ["Splats", "SH_C0", "rgb_to_sh_dc", "sh_dc_to_rgb", "sh_degree_of", "view_dependent_colors"]


def sh_dc_to_rgb(sh_dc: torch.Tensor) -> torch.Tensor:
    """SH DC coefficients [..., 3] -> RGB in [0, 1]."""
    return (0.5 + SH_C0 * sh_dc).clamp(0.0, 1.0)


def rgb_to_sh_dc(rgb: torch.Tensor) -> torch.Tensor:
    """RGB in [0, 1] [..., 3] -> SH DC coefficients."""
    return (rgb - 0.5) / SH_C0


def sh_degree_of(sh_rest: torch.Tensor) -> int:
    """Highest complete SH degree that ``sh_rest`` [N, K, 3] holds (K = 0, 3, 8, 15 -> 0..3)."""
    k = int(sh_rest.shape[1])
    for degree in (3, 2, 1):
        if k >= (degree + 1) ** 2 - 1:
            return degree
    return 0


def view_dependent_colors(means: torch.Tensor, sh_dc: torch.Tensor, sh_rest: torch.Tensor, centres: torch.Tensor,
                          degree: Optional[int] = None) -> torch.Tensor:
    """RGB of every splat as seen from each of C camera centres, evaluated before rasterising.

    Args:
        means: [N, 3] splat centres; sh_dc: [N, 3]; sh_rest: [N, K, 3] higher SH bands;
        centres: [C, 3] camera centres, same frame as ``means``;
        degree: SH degree 0..3 (None: the highest that ``sh_rest`` holds).
    Returns:
        [C, N, 3] colours in [0, 1] (3DGS basis and sign convention, viewing direction =
        camera centre -> splat), differentiable w.r.t. means, sh_dc and sh_rest; the
        per-camera colours that :func:`soma_ros.core.render.render` accepts. Degree 0 gives
        ``sh_dc_to_rgb(sh_dc)`` for every camera.
    """
    from .render import eval_sh

    n = means.shape[0]
    if means.ndim != 2 or means.shape[1] != 3:
        raise ValueError(f"view_dependent_colors: means must be [N, 3], got {list(means.shape)}")
    if tuple(sh_dc.shape) != (n, 3) or sh_rest.ndim != 3 or sh_rest.shape[0] != n or sh_rest.shape[2] != 3:
        raise ValueError(f"view_dependent_colors: sh_dc must be [{n}, 3] and sh_rest [{n}, K, 3], got "
                         f"{list(sh_dc.shape)} and {list(sh_rest.shape)}")
    if centres.ndim != 2 or centres.shape[1] != 3:
        raise ValueError(f"view_dependent_colors: centres must be [C, 3], got {list(centres.shape)}")
    degree = sh_degree_of(sh_rest) if degree is None else int(degree)
    if degree == 0:
        return sh_dc_to_rgb(sh_dc)[None].expand(centres.shape[0], n, 3)
    dirs = means[None, :, :] - centres.to(means)[:, None, :]  # [C, N, 3]
    dirs = dirs / dirs.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    out = eval_sh(sh_dc, sh_rest, dirs, degree)
    assert out.shape == (centres.shape[0], n, 3)
    return out


@dataclass
class Splats:
    means: torch.Tensor
    quats: torch.Tensor
    scales: torch.Tensor
    opacities: torch.Tensor
    sh_dc: torch.Tensor
    sh_rest: Optional[torch.Tensor] = None
    mass: Optional[torch.Tensor] = None
    attrs: Optional[torch.Tensor] = None
    extra: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        n = self.means.shape[0] if self.means.ndim == 2 else -1
        if self.means.ndim != 2 or self.means.shape[1] != 3:
            raise ValueError(f"Splats.means must be [N, 3], got {tuple(self.means.shape)}")
        expect = {
            "quats": (n, 4),
            "scales": (n, 3),
            "opacities": (n,),
            "sh_dc": (n, 3),
        }
        for name, shape in expect.items():
            t = getattr(self, name)
            if tuple(t.shape) != shape:
                raise ValueError(f"Splats.{name} must be {list(shape)}, got {list(t.shape)}")
        if self.sh_rest is None:
            self.sh_rest = self.means.new_zeros((n, 0, 3))
        if self.sh_rest.ndim != 3 or self.sh_rest.shape[0] != n or self.sh_rest.shape[2] != 3:
            raise ValueError(f"Splats.sh_rest must be [N, K, 3], got {list(self.sh_rest.shape)}")
        if self.mass is None:
            self.mass = self.means.new_full((n,), 1.0 / max(n, 1))
        if tuple(self.mass.shape) != (n,):
            raise ValueError(f"Splats.mass must be [N], got {list(self.mass.shape)}")
        if self.attrs is None:
            self.attrs = self.means.new_zeros((n, 0))
        if self.attrs.ndim != 2 or self.attrs.shape[0] != n:
            raise ValueError(f"Splats.attrs must be [N, A], got {list(self.attrs.shape)}")

    # ------------------------------------------------------------------ basics
    def __len__(self) -> int:
        return int(self.means.shape[0])

    @property
    def device(self) -> torch.device:
        return self.means.device

    def to(self, device=None, dtype=None) -> "Splats":
        def mv(t):
            if t is None:
                return None
            return t.to(device=device, dtype=dtype if t.is_floating_point() else None)

        return replace(
            self,
            means=mv(self.means),
            quats=mv(self.quats),
            scales=mv(self.scales),
            opacities=mv(self.opacities),
            sh_dc=mv(self.sh_dc),
            sh_rest=mv(self.sh_rest),
            mass=mv(self.mass),
            attrs=mv(self.attrs),
        )

    def detach(self) -> "Splats":
        return replace(
            self,
            means=self.means.detach(),
            quats=self.quats.detach(),
            scales=self.scales.detach(),
            opacities=self.opacities.detach(),
            sh_dc=self.sh_dc.detach(),
            sh_rest=self.sh_rest.detach(),
            mass=self.mass.detach(),
            attrs=self.attrs.detach(),
        )

    def index(self, idx) -> "Splats":
        """Subset by an index tensor or boolean mask over N."""
        return Splats(
            means=self.means[idx],
            quats=self.quats[idx],
            scales=self.scales[idx],
            opacities=self.opacities[idx],
            sh_dc=self.sh_dc[idx],
            sh_rest=self.sh_rest[idx],
            mass=self.mass[idx],
            attrs=self.attrs[idx],
        )

    # ------------------------------------------------------------ derived data
    def colors(self) -> torch.Tensor:
        """View-independent RGB [N, 3] in [0, 1] (SH degree 0)."""
        return sh_dc_to_rgb(self.sh_dc)

    def colors_seen_from(self, centres: torch.Tensor, degree: Optional[int] = None) -> torch.Tensor:
        """View-dependent RGB [C, N, 3] from camera centres [C, 3] (see :func:`view_dependent_colors`)."""
        return view_dependent_colors(self.means, self.sh_dc, self.sh_rest, centres, degree)

    def covariances(self) -> torch.Tensor:
        """3D covariances [N, 3, 3] = R diag(scales^2) R^T."""
        return covariance_from_scale_rot(self.scales, quat_normalize(self.quats))

    def validate(self) -> None:
        """Raise ValueError naming the first problem (non-finite values, bad ranges)."""
        for name in ("means", "quats", "scales", "opacities", "sh_dc", "mass"):
            t = getattr(self, name)
            if not torch.isfinite(t).all():
                bad = int((~torch.isfinite(t)).reshape(t.shape[0], -1).any(-1).sum())
                raise ValueError(f"Splats.{name} has non-finite values in {bad} splats")
        if (self.scales <= 0).any():
            raise ValueError("Splats.scales must be > 0")
        if ((self.opacities < 0) | (self.opacities > 1)).any():
            raise ValueError("Splats.opacities must lie in [0, 1]")
        if (self.quats.norm(dim=-1) < 1e-8).any():
            raise ValueError("Splats.quats has zero-length quaternions")
        if (self.mass < 0).any():
            raise ValueError("Splats.mass must be >= 0")

    @staticmethod
    def from_points(
        points: torch.Tensor,
        colors: Optional[torch.Tensor] = None,
        scale: float = 0.005,
        opacity: float = 0.9,
        total_mass: float = 1.0,
    ) -> "Splats":
        """Isotropic splats at ``points`` [N, 3] with RGB ``colors`` [N, 3] in [0, 1]."""
        n = points.shape[0]
        if colors is None:
            colors = points.new_full((n, 3), 0.5)
        quats = points.new_zeros((n, 4))
        quats[:, 0] = 1.0
        return Splats(
            means=points,
            quats=quats,
            scales=points.new_full((n, 3), float(scale)),
            opacities=points.new_full((n,), float(opacity)),
            sh_dc=rgb_to_sh_dc(colors),
            mass=points.new_full((n,), total_mass / max(n, 1)),
        )
