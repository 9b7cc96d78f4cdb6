"""Differentiable Gaussian-splat renderer (pure torch reference, gsplat on CUDA).

Entry points
------------
``render(means [N,3], covs [N,3,3], colors [N,3] or [C,N,3], opacities [N],
cameras, background=None, cfg=None) -> RenderOutput`` and
``render_splats(splats, cameras, background=None, cfg=None)``.

Outputs (:class:`RenderOutput`), C cameras of H x W pixels:

* ``rgb   [C, H, W, 3]`` composited colour ``premultiplied + (1 - alpha) * background``
* ``depth [C, H, W]``    expected depth ``sum_i w_i z_i / alpha`` (camera-frame z of
  the splat means, metres); exactly 0 where ``alpha < cfg.depth_alpha_eps``
* ``alpha [C, H, W]``    accumulated opacity ``sum_i w_i = 1 - T_final``
* ``premultiplied [C, H, W, 3]`` the colour before the background is added

Premultiplied alpha and background
----------------------------------
Front-to-back compositing gives ``w_i = alpha_i prod_{j<i} (1 - alpha_j)``;
the *premultiplied* colour of a pixel is ``sum_i w_i c_i`` (what gsplat returns
without a background). ``rgb`` adds the background behind the splats:
``rgb = premultiplied + (1 - alpha) * background``; ``background`` is an RGB
colour [3] or one per camera [C, 3]; ``None`` means black, so that ``rgb`` is
then the premultiplied colour -- the "object over a black background" image
that the masked metrics of :mod:`soma_ros.core.metrics` expect.

Conventions (those of gsplat's "classic" mode, except ``alpha_max``)
--------------------------------------------------------------------
* Cameras: OpenCV optical frame (x right, y down, z forward), ``world_to_cam``
  view matrices, pinhole ``K`` in pixels; pixel (col, row) centre at
  (col + 0.5, row + 0.5). See :mod:`soma_ros.core.cameras`.
* EWA splatting: ``cov2d = J W Sigma W^T J^T + eps2d * I`` with J the Jacobian
  of the perspective map at the mean (x/z and y/z clamped to 1.3x the field of
  view as gsplat does, only inside J); ``eps2d = 0.3``.
* Splats with camera z outside [near_plane, far_plane] (near 0.01 m) are culled.
* A splat contributes to a pixel iff its alpha ``opacity * exp(-power)`` is
  >= ``alpha_min`` (1/255) and the pixel is inside its ``sigma_cutoff`` (3)
  sigma ellipse; alpha is clamped to ``alpha_max = 0.99`` (3DGS value; gsplat
  uses 0.999); front to back, compositing stops before the splat that would
  take the transmittance to <= ``transmittance_min`` (1e-4).
* Splats are sorted front to back by camera z of their means, per tile.

Gradients flow to means, covs, colors and opacities (the torch path uses an
analytic backward for the compositing, see :mod:`render_raster`). The torch
path is the reference; ``cfg.backend = "auto"`` uses ``gsplat.rasterization``
when gsplat imports and the inputs are on CUDA.

Pure torch; no ROS imports.
"""

from __future__ import annotations

import functools
import importlib
import math
from dataclasses import dataclass
from typing import Optional

import torch

from . import raster_kernel
from .cameras import Cameras
from .render_raster import Projected, build_plan, composite

__all__ = [
    "RenderConfig",
    "RenderOutput",
    "Projected",
    "project_gaussians",
    "render",
    "render_splats",
    "eval_sh",
    "gsplat_available",
]


@dataclass
class RenderConfig:
    """Renderer settings (defaults follow gsplat / 3DGS, see module docstring).

    ``tile_size`` and ``max_chunk_elems`` only affect speed and memory of the
    torch path, not the image (8 and 2**17 were fastest on a 2-core Xeon CPU;
    gsplat always uses its 16 px tiles). ``tile_cull`` likewise.
    """

    tile_size: int = 8
    near_plane: float = 0.01
    far_plane: float = 1e10
    eps2d: float = 0.3
    sigma_cutoff: float = 3.0
    alpha_min: float = 1.0 / 255.0
    alpha_max: float = 0.99
    transmittance_min: float = 1e-4
    depth_alpha_eps: float = 1e-10
    clamp_jacobian: bool = True
    # at most this many (pixel, splat) pairs are evaluated at once (memory bound)
    max_chunk_elems: int = 1 << 17
    # drop tiles inside a splat's bounding box that its cut-off ellipse misses
    tile_cull: bool = True
    # "auto": gsplat on CUDA when importable, else torch; "torch"; "gsplat"
    backend: str = "auto"
    # compositor of the torch backend on CPU: "auto" the compiled kernels of
    # raster_kernel when they load (else the reference, with one warning line),
    # "torch" always the pure-torch reference, "compiled" the kernels or an error
    raster: str = "auto"

    def __post_init__(self) -> None:
        if self.tile_size < 1:
            raise ValueError(f"RenderConfig.tile_size must be >= 1, got {self.tile_size}")
        if not 0 < self.near_plane < self.far_plane:
            raise ValueError("RenderConfig needs 0 < near_plane < far_plane")
        if self.eps2d < 0:
            raise ValueError("RenderConfig.eps2d must be >= 0")
        if self.sigma_cutoff <= 0:
            raise ValueError("RenderConfig.sigma_cutoff must be > 0")
        if not 0 < self.alpha_min < self.alpha_max < 1:
            raise ValueError("RenderConfig needs 0 < alpha_min < alpha_max < 1")
        if not 0 <= self.transmittance_min < 1:
            raise ValueError("RenderConfig.transmittance_min must lie in [0, 1)")
        if self.max_chunk_elems < 1:
            raise ValueError("RenderConfig.max_chunk_elems must be >= 1")
        if self.backend not in ("auto", "torch", "gsplat"):
            raise ValueError(f"RenderConfig.backend must be auto|torch|gsplat, got {self.backend!r}")
        if self.raster not in ("auto", "torch", "compiled"):
            raise ValueError(f"RenderConfig.raster must be auto|torch|compiled, got {self.raster!r}")


@dataclass
class RenderOutput:
    """Rendered images of C cameras; see the module docstring for semantics."""

    rgb: torch.Tensor  # [C, H, W, 3]
    depth: torch.Tensor  # [C, H, W]
    alpha: torch.Tensor  # [C, H, W]
    premultiplied: torch.Tensor  # [C, H, W, 3]
    backend: str = "torch"  # "torch" (reference), "compiled" (CPU kernels) or "gsplat"
    n_visible: int = 0  # visible (camera, splat) pairs
    n_isect: int = 0  # (tile, splat) intersections (torch backend)

    def rgb_u8(self) -> torch.Tensor:
        """The images as 8-bit colour [C, H, W, 3] (clamped to [0, 1], rounded), as published."""
        return (self.rgb.clamp(0, 1) * 255).round().to(torch.uint8)


@functools.lru_cache(maxsize=1)
def gsplat_available() -> bool:
    """True when ``import gsplat`` works (the CUDA backend can be tried); cached."""
    try:
        importlib.import_module("gsplat")
    except Exception:
        return False
    return True


def _check_inputs(means, covs, colors, opacities, cameras):
    if not isinstance(cameras, Cameras):
        raise TypeError(f"cameras must be a Cameras, got {type(cameras).__name__}")
    if means.ndim != 2 or means.shape[1] != 3:
        raise ValueError(f"render: means must be [N, 3], got {list(means.shape)}")
    N = means.shape[0]
    C = len(cameras)
    if tuple(covs.shape) != (N, 3, 3):
        raise ValueError(f"render: covs must be [N, 3, 3] = [{N}, 3, 3], got {list(covs.shape)}")
    if tuple(opacities.shape) != (N,):
        raise ValueError(f"render: opacities must be [N] = [{N}], got {list(opacities.shape)}")
    if tuple(colors.shape) not in ((N, 3), (C, N, 3)):
        raise ValueError(
            f"render: colors must be [N, 3] or [C, N, 3] = [{C}, {N}, 3], got {list(colors.shape)}"
        )
    for name, t in (("covs", covs), ("colors", colors), ("opacities", opacities)):
        if t.device != means.device:
            raise ValueError(f"render: {name} is on {t.device}, means on {means.device}")
        if not t.is_floating_point():
            raise ValueError(f"render: {name} must be floating point")


def project_gaussians(
    means: torch.Tensor,
    covs: torch.Tensor,
    opacities: torch.Tensor,
    cameras: Cameras,
    cfg: RenderConfig,
) -> Projected:
    """EWA projection of N 3D Gaussians into C cameras with culling (differentiable).

    Args:
        means: [N, 3] world positions; covs: [N, 3, 3] world covariances;
        opacities: [N] in [0, 1].
    Returns:
        :class:`Projected` with the V (camera, splat) pairs that can touch a pixel.
    """
    dt = means.dtype
    dev = means.device
    W, H = cameras.width, cameras.height
    Rw = cameras.world_to_cam[:, :3, :3].to(device=dev, dtype=dt)  # [C, 3, 3]
    tw = cameras.world_to_cam[:, :3, 3].to(device=dev, dtype=dt)  # [C, 3]
    K = cameras.K.to(device=dev, dtype=dt)
    with torch.no_grad():
        z_all = torch.einsum("cj,nj->cn", Rw[:, 2], means) + tw[:, None, 2]  # [C, N]
        ok = (z_all > cfg.near_plane) & (z_all < cfg.far_plane)
        ok &= (opacities >= cfg.alpha_min)[None, :]
        cam_idx, splat_idx = torch.nonzero(ok, as_tuple=True)
    R = Rw[cam_idx]  # [V, 3, 3]
    pc = (R @ means[splat_idx][:, :, None])[:, :, 0] + tw[cam_idx]  # [V, 3]
    x, y, z = pc.unbind(-1)
    fx, fy = K[cam_idx, 0, 0], K[cam_idx, 1, 1]
    cx, cy = K[cam_idx, 0, 2], K[cam_idx, 1, 2]
    inv_z = 1.0 / z
    u = fx * x * inv_z + cx
    v = fy * y * inv_z + cy
    # Jacobian of (fx x/z + cx, fy y/z + cy) at the mean, x/z and y/z clamped like gsplat
    xz = x * inv_z
    yz = y * inv_z
    if cfg.clamp_jacobian:
        tan_fovx = 0.5 * W / fx
        tan_fovy = 0.5 * H / fy
        lim_xp = (W - cx) / fx + 0.3 * tan_fovx
        lim_xn = cx / fx + 0.3 * tan_fovx
        lim_yp = (H - cy) / fy + 0.3 * tan_fovy
        lim_yn = cy / fy + 0.3 * tan_fovy
        xz = torch.minimum(torch.maximum(xz, -lim_xn), lim_xp)
        yz = torch.minimum(torch.maximum(yz, -lim_yn), lim_yp)
    j00 = fx * inv_z
    j02 = -fx * xz * inv_z
    j11 = fy * inv_z
    j12 = -fy * yz * inv_z
    Sc = R @ covs[splat_idx] @ R.transpose(1, 2)  # [V, 3, 3] camera-frame covariance
    s00, s01, s02 = Sc[:, 0, 0], Sc[:, 0, 1], Sc[:, 0, 2]
    s11, s12, s22 = Sc[:, 1, 1], Sc[:, 1, 2], Sc[:, 2, 2]
    sxx = j00 * j00 * s00 + 2.0 * j00 * j02 * s02 + j02 * j02 * s22 + cfg.eps2d
    sxy = j00 * j11 * s01 + j00 * j12 * s02 + j02 * j11 * s12 + j02 * j12 * s22
    syy = j11 * j11 * s11 + 2.0 * j11 * j12 * s12 + j12 * j12 * s22 + cfg.eps2d
    det = sxx * syy - sxy * sxy
    op = opacities[splat_idx]
    with torch.no_grad():
        logo = torch.log(op)
        smin = torch.clamp(logo - 0.5 * cfg.sigma_cutoff**2, min=math.log(cfg.alpha_min))
        pmax = logo - smin
        good = (det > 0) & torch.isfinite(u) & torch.isfinite(v)
        # splats whose cut-off box misses the image entirely
        hx = torch.sqrt(2.0 * pmax * sxx.clamp_min(0)) + 1.0
        hy = torch.sqrt(2.0 * pmax * syy.clamp_min(0)) + 1.0
        good &= (u + hx > 0) & (u - hx < W) & (v + hy > 0) & (v - hy < H)
        sel = torch.nonzero(good, as_tuple=False)[:, 0]
    det = det[sel]
    sxx, sxy, syy = sxx[sel], sxy[sel], syy[sel]
    conic = torch.stack([syy / det, -sxy / det, sxx / det], dim=-1)
    return Projected(
        cam_idx=cam_idx[sel],
        splat_idx=splat_idx[sel],
        mean2d=torch.stack([u[sel], v[sel]], dim=-1),
        conic=conic,
        cov2d=torch.stack([sxx, sxy, syy], dim=-1),
        depth=z[sel],
        opacity=op[sel],
        smin=smin[sel],
        pmax=pmax[sel],
    )


def _background(background: Optional[torch.Tensor], C: int, dtype, device) -> torch.Tensor:
    if background is None:
        return torch.zeros(C, 3, dtype=dtype, device=device)
    bg = torch.as_tensor(background, dtype=dtype, device=device)
    if bg.shape == (3,):
        return bg[None].expand(C, 3)
    if bg.shape == (C, 3):
        return bg
    raise ValueError(f"render: background must be [3] or [C, 3] = [{C}, 3], got {list(bg.shape)}")


def _finish(premult, dsum, alpha, bg, cfg, backend, n_vis, n_isect) -> RenderOutput:
    rgb = premult + (1.0 - alpha)[..., None] * bg[:, None, None, :]
    has = alpha >= cfg.depth_alpha_eps
    depth = torch.where(has, dsum / torch.where(has, alpha, torch.ones_like(alpha)), torch.zeros_like(alpha))
    return RenderOutput(rgb=rgb, depth=depth, alpha=alpha, premultiplied=premult,
                        backend=backend, n_visible=n_vis, n_isect=n_isect)


def _use_kernels(means: torch.Tensor, cfg: RenderConfig) -> bool:
    """Whether the compiled CPU kernels composite this render (see ``RenderConfig.raster``)."""
    if cfg.raster == "torch" or means.device.type != "cpu" or means.dtype not in (torch.float32, torch.float64):
        if cfg.raster == "compiled":
            raise ValueError("render: raster 'compiled' needs float32/float64 CPU tensors")
        return False
    if raster_kernel.available():
        return True
    if cfg.raster == "compiled":
        raise ImportError(f"render: raster 'compiled' requested but the kernels are unavailable "
                          f"({raster_kernel.unavailable_reason()})")
    return False


def _render_torch(means, covs, colors, opacities, cameras, bg, cfg) -> RenderOutput:
    C = len(cameras)
    kernels = _use_kernels(means, cfg)
    camera_grad = torch.is_grad_enabled() and (cameras.world_to_cam.requires_grad or cameras.K.requires_grad)
    if kernels and not camera_grad:
        proj = raster_kernel.project(means, covs, opacities, cameras, cfg)
    else:
        proj = project_gaussians(means, covs, opacities, cameras, cfg)
    V = proj.mean2d.shape[0]
    if colors.ndim == 3:
        col = colors[proj.cam_idx, proj.splat_idx]
    else:
        col = colors[proj.splat_idx]
    feat = torch.cat([col, proj.depth[:, None], torch.ones_like(proj.depth)[:, None]], dim=-1)
    if kernels:
        kplan = raster_kernel.bin_splats(proj.mean2d, proj.conic, proj.cov2d, proj.pmax, proj.depth,
                                         proj.cam_idx, C, cameras.width, cameras.height, cfg.tile_size)
        img = raster_kernel.composite(proj.mean2d, proj.conic, proj.opacity, feat.to(means.dtype), proj.smin,
                                      kplan, cfg.alpha_max, cfg.transmittance_min)
        name, n_isect = "compiled", kplan.n_isect
    else:
        plan = build_plan(
            proj.mean2d.detach(),
            proj.conic.detach(),
            proj.cov2d.detach()[:, [0, 2]],
            proj.pmax,
            proj.depth.detach(),
            proj.cam_idx,
            C,
            cameras.width,
            cameras.height,
            cfg.tile_size,
            cfg.max_chunk_elems,
            cfg.tile_cull,
        )
        img = composite(proj.mean2d, proj.conic, proj.opacity, feat, proj.smin, plan,
                        cfg.alpha_max, cfg.transmittance_min)  # [C, H, W, 5]
        name, n_isect = "torch", plan.n_isect
    if img.shape != (C, cameras.height, cameras.width, 5):
        raise RuntimeError(f"render: compositor returned {list(img.shape)}, expected [C, H, W, 5]")
    # one split (its backward is one concatenation) rather than three slices (three zeroed images)
    premult, dsum, alpha = img.split([3, 1, 1], dim=-1)
    return _finish(premult, dsum[..., 0], alpha[..., 0], bg, cfg, name, V, n_isect)


def _render_gsplat(means, covs, colors, opacities, cameras, bg, cfg) -> RenderOutput:
    import gsplat

    C = len(cameras)
    viewmats = cameras.world_to_cam.to(device=means.device, dtype=means.dtype)
    Ks = cameras.K.to(device=means.device, dtype=means.dtype)
    out, alphas, meta = gsplat.rasterization(
        means=means,
        quats=None,
        scales=None,
        opacities=opacities,
        colors=colors,
        viewmats=viewmats,
        Ks=Ks,
        width=cameras.width,
        height=cameras.height,
        near_plane=cfg.near_plane,
        far_plane=cfg.far_plane,
        eps2d=cfg.eps2d,
        tile_size=16,  # gsplat's tuned CUDA tile; cfg.tile_size is for the torch path
        render_mode="RGB+ED",
        rasterize_mode="classic",
        covars=covs,
        packed=False,
    )
    if out.shape != (C, cameras.height, cameras.width, 4):
        raise RuntimeError(f"gsplat returned {list(out.shape)}, expected [C, H, W, 4]")
    alpha = alphas[..., 0]
    premult = out[..., :3]
    # gsplat's "ED" is D / max(alpha, 1e-10); convert back to D for _finish
    dsum = out[..., 3] * alpha
    n_vis = 0
    if isinstance(meta, dict) and "radii" in meta:
        r = meta["radii"]  # [C, N] (older gsplat) or [C, N, 2]
        n_vis = int(((r > 0).all(-1) if r.ndim == 3 else (r > 0)).sum())
    return _finish(premult, dsum, alpha, bg, cfg, "gsplat", n_vis, 0)


def render(
    means: torch.Tensor,
    covs: torch.Tensor,
    colors: torch.Tensor,
    opacities: torch.Tensor,
    cameras: Cameras,
    background: Optional[torch.Tensor] = None,
    cfg: Optional[RenderConfig] = None,
) -> RenderOutput:
    """Render N Gaussians into the C cameras of ``cameras``.

    Args:
        means: [N, 3] world positions (metres).
        covs: [N, 3, 3] world covariances (symmetric positive definite).
        colors: [N, 3] RGB or [C, N, 3] per-camera RGB (e.g. view-dependent SH).
        opacities: [N] in [0, 1].
        cameras: :class:`Cameras` (C cameras, H x W).
        background: None (black), [3] or [C, 3] colour behind the splats.
        cfg: :class:`RenderConfig`; defaults if None.
    Returns:
        :class:`RenderOutput` with rgb [C,H,W,3], depth [C,H,W], alpha [C,H,W].
    """
    cfg = cfg or RenderConfig()
    _check_inputs(means, covs, colors, opacities, cameras)
    bg = _background(background, len(cameras), means.dtype, means.device)
    backend = cfg.backend
    if backend == "auto":
        use = means.is_cuda and means.dtype == torch.float32 and gsplat_available()
        backend = "gsplat" if use else "torch"
    if backend == "gsplat":
        if not means.is_cuda:
            raise ValueError("render: backend 'gsplat' needs CUDA tensors")
        if not gsplat_available():
            raise ImportError("render: backend 'gsplat' requested but gsplat does not import")
        return _render_gsplat(means, covs, colors, opacities, cameras, bg, cfg)
    return _render_torch(means, covs, colors, opacities, cameras, bg, cfg)


# ----------------------------------------------------------------- SH colours
_SH_C0 = 0.28209479177387814
_SH_C1 = 0.4886025119029199
_SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005,
          -1.0925484305920792, 0.5462742152960396)
_SH_C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
          -0.4570457994644658, 1.445305721320277, -0.5900435899266435)


def eval_sh(sh_dc: torch.Tensor, sh_rest: torch.Tensor, dirs: torch.Tensor, degree: int) -> torch.Tensor:
    """View-dependent RGB from real spherical harmonics (3DGS basis and sign convention).

    Args:
        sh_dc: [N, 3]; sh_rest: [N, K, 3] (K >= (degree+1)^2 - 1); dirs: [..., N, 3]
        unit viewing directions (camera centre -> splat, world frame); degree 0..3.
    Returns:
        [..., N, 3] colours ``clamp(0.5 + sum_lm Y_lm(d) * coeff_lm, 0, 1)``.
    """
    if not 0 <= degree <= 3:
        raise ValueError(f"eval_sh: degree must be 0..3, got {degree}")
    n_rest = (degree + 1) ** 2 - 1
    if sh_rest.shape[1] < n_rest:
        raise ValueError(f"eval_sh: degree {degree} needs {n_rest} rest coefficients, have {sh_rest.shape[1]}")
    res = _SH_C0 * sh_dc.expand(dirs.shape)
    if degree >= 1:
        x, y, z = dirs[..., 0:1], dirs[..., 1:2], dirs[..., 2:3]
        r = sh_rest
        res = res - _SH_C1 * y * r[:, 0] + _SH_C1 * z * r[:, 1] - _SH_C1 * x * r[:, 2]
        if degree >= 2:
            xx, yy, zz = x * x, y * y, z * z
            xy, yz, xz = x * y, y * z, x * z
            res = (res + _SH_C2[0] * xy * r[:, 3] + _SH_C2[1] * yz * r[:, 4]
                   + _SH_C2[2] * (2.0 * zz - xx - yy) * r[:, 5]
                   + _SH_C2[3] * xz * r[:, 6] + _SH_C2[4] * (xx - yy) * r[:, 7])
            if degree >= 3:
                res = (res + _SH_C3[0] * y * (3.0 * xx - yy) * r[:, 8]
                       + _SH_C3[1] * xy * z * r[:, 9]
                       + _SH_C3[2] * y * (4.0 * zz - xx - yy) * r[:, 10]
                       + _SH_C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy) * r[:, 11]
                       + _SH_C3[4] * x * (4.0 * zz - xx - yy) * r[:, 12]
                       + _SH_C3[5] * z * (xx - yy) * r[:, 13]
                       + _SH_C3[6] * x * (xx - 3.0 * yy) * r[:, 14])
    return (res + 0.5).clamp(0.0, 1.0)


def render_splats(
    splats,
    cameras: Cameras,
    background: Optional[torch.Tensor] = None,
    cfg: Optional[RenderConfig] = None,
    sh_degree: Optional[int] = 0,
) -> RenderOutput:
    """Render a :class:`~soma_ros.core.splats.Splats`.

    ``sh_degree`` 0 uses ``splats.colors()``; 1..3 evaluates view-dependent
    colour per camera from ``sh_dc``/``sh_rest``; None uses the highest degree
    that ``sh_rest`` holds.
    """
    n_rest = splats.sh_rest.shape[1]
    if sh_degree is None:
        sh_degree = {0: 0, 3: 1, 8: 2, 15: 3}.get(n_rest, 0)
    if sh_degree == 0:
        colors = splats.colors()
    else:
        centres = cameras.centers().to(device=splats.means.device, dtype=splats.means.dtype)
        dirs = splats.means[None, :, :] - centres[:, None, :]  # [C, N, 3]
        dirs = dirs / dirs.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        colors = eval_sh(splats.sh_dc, splats.sh_rest, dirs, sh_degree)
    return render(splats.means, splats.covariances(), colors, splats.opacities, cameras,
                  background=background, cfg=cfg)
