"""Image and depth metrics of the SoMA / PhysTwin evaluation, and the training loss.

Shapes: RGB images are ``[H, W, 3]`` or ``[B, H, W, 3]`` in [0, 1]; masks and
depth maps ``[H, W]`` or ``[B, H, W]`` (a trailing singleton channel is
accepted). Masks may be bool or float in [0, 1] (> 0.5 counts as set where a
binary decision is needed). Each metric returns a 0-dim tensor for an
unbatched input and a ``[B]`` tensor (one value per image) for a batch; call
``.item()`` / ``.tolist()`` for floats. :func:`image_metrics` and
:func:`depth_metrics` return plain ``dict[str, float]`` means over the batch.

Evaluation protocol (paper Sec. "Evaluation Metrics"; PhysTwin's code)
----------------------------------------------------------------------
* Image metrics (PSNR, SSIM, LPIPS) compare the rendered object (rendered over
  a black background, i.e. ``RenderOutput.rgb`` with ``background=None``) with
  ``GT x object_mask`` (object on black), both multiplied by
  ``(1 - robot_mask)`` so robot-occluded pixels count as black in both; the
  metrics are then taken over the whole image (:func:`apply_eval_masks`,
  :func:`image_metrics`). ``psnr(..., mask=...)`` additionally offers the PSNR
  of the masked pixels only.
* Depth metrics (AbsRel ``mean |d - d*| / d*``, RMSE ``sqrt(mean (d - d*)^2)``,
  metres) use the valid object pixels ``object_mask & gt > 0 & ~robot_mask``;
  pixels where nothing was rendered (depth 0) count as errors.
* SSIM: Gaussian window 11x11, sigma 1.5, K = (0.01, 0.03), no padding ("valid",
  the pytorch-msssim / Wang et al. convention), mean over pixels and channels.
* LPIPS: AlexNet v0.1 (:mod:`soma_ros.core.lpips`), inputs in [0, 1].
"""

from __future__ import annotations

import math
from typing import Optional

import torch
import torch.nn.functional as F

from .lpips import LPIPS, lpips_distance

__all__ = [
    "psnr",
    "masked_psnr",
    "ssim",
    "ssim_map",
    "lpips",
    "depth_abs_rel",
    "depth_rmse",
    "apply_eval_masks",
    "image_metrics",
    "depth_metrics",
    "masked_l2_dssim_loss",
]


# ------------------------------------------------------------------ helpers
def _rgb_batch(x: torch.Tensor, name: str) -> tuple[torch.Tensor, bool]:
    if not isinstance(x, torch.Tensor):
        raise TypeError(f"{name} must be a torch.Tensor, got {type(x).__name__}")
    if x.ndim == 3 and x.shape[-1] == 3:
        return x[None], True
    if x.ndim == 4 and x.shape[-1] == 3:
        return x, False
    raise ValueError(f"{name} must be [H, W, 3] or [B, H, W, 3], got {list(x.shape)}")


def _map_batch(x: Optional[torch.Tensor], name: str, like: torch.Tensor) -> Optional[torch.Tensor]:
    """Mask / depth [H,W], [B,H,W] (or with a trailing 1) -> float [B,H,W] matching ``like`` [B,H,W,...]."""
    if x is None:
        return None
    if not isinstance(x, torch.Tensor):
        x = torch.as_tensor(x)
    if x.ndim >= 3 and x.shape[-1] == 1 and x.shape[-3:-1] == like.shape[1:3]:
        x = x[..., 0]
    if x.ndim == 2:
        x = x[None]
    B, H, W = like.shape[:3]
    if x.ndim != 3 or x.shape[1:] != (H, W) or x.shape[0] not in (1, B):
        raise ValueError(f"{name} must be [H, W] or [B, H, W] = [{B}, {H}, {W}], got {list(x.shape)}")
    x = x.to(device=like.device)
    x = x.to(like.dtype if like.is_floating_point() else torch.float32)
    return x.expand(B, H, W)


def _depth_batch(x: torch.Tensor, name: str) -> tuple[torch.Tensor, bool]:
    if x.ndim == 3 and x.shape[-1] == 1:
        x = x[..., 0]
    if x.ndim == 2:
        return x[None], True
    if x.ndim == 3:
        return x, False
    raise ValueError(f"{name} must be [H, W] or [B, H, W], got {list(x.shape)}")


def _out(v: torch.Tensor, single: bool) -> torch.Tensor:
    return v[0] if single else v


def _gauss_window(size: int, sigma: float, dtype, device) -> torch.Tensor:
    x = torch.arange(size, dtype=dtype, device=device) - (size - 1) / 2.0
    g = torch.exp(-(x * x) / (2.0 * sigma * sigma))
    return g / g.sum()


def _blur(x: torch.Tensor, g: torch.Tensor, padding: str) -> torch.Tensor:
    """Separable Gaussian blur of [N, C, H, W] (depthwise), 'valid' or 'same' (zero pad)."""
    C = x.shape[1]
    k = g.numel()
    pad = k // 2 if padding == "same" else 0
    wx = g.view(1, 1, 1, k).expand(C, 1, 1, k)
    wy = g.view(1, 1, k, 1).expand(C, 1, k, 1)
    x = F.conv2d(x, wx, padding=(0, pad), groups=C)
    return F.conv2d(x, wy, padding=(pad, 0), groups=C)


# ------------------------------------------------------------------ image metrics
def psnr(pred: torch.Tensor, gt: torch.Tensor, mask: Optional[torch.Tensor] = None,
         max_val: float = 1.0) -> torch.Tensor:
    """PSNR in dB, ``10 log10(max_val^2 / MSE)``; MSE over all pixels and channels,
    or, with ``mask``, the mask-weighted mean over the masked pixels (NaN if empty).
    Identical images give +inf."""
    p, single = _rgb_batch(pred, "pred")
    g, _ = _rgb_batch(gt, "gt")
    if p.shape != g.shape:
        raise ValueError(f"psnr: pred {list(p.shape)} and gt {list(g.shape)} differ")
    err = (p.double() - g.double()).square().sum(-1)  # [B, H, W]
    m = _map_batch(mask, "mask", p)
    if m is None:
        mse = err.mean(dim=(1, 2)) / 3.0
    else:
        m = m.double()
        mse = (err * m).sum(dim=(1, 2)) / (3.0 * m.sum(dim=(1, 2)))
    return _out(10.0 * torch.log10(max_val**2 / mse), single).to(p.dtype if p.is_floating_point() else torch.float64)


def masked_psnr(pred: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor, max_val: float = 1.0) -> torch.Tensor:
    """PSNR over the pixels where ``mask`` is set (``psnr(pred, gt, mask=mask)``)."""
    if mask is None:
        raise ValueError("masked_psnr needs a mask (use psnr for the whole image)")
    return psnr(pred, gt, mask=mask, max_val=max_val)


def ssim_map(pred: torch.Tensor, gt: torch.Tensor, window_size: int = 11, sigma: float = 1.5,
             padding: str = "valid", max_val: float = 1.0,
             k: tuple[float, float] = (0.01, 0.03)) -> torch.Tensor:
    """Per-pixel SSIM averaged over channels: [B,H,W,3] pairs -> [B, H', W'].

    ``padding="valid"``: H' = H - window_size + 1 (no border effects);
    ``"same"``: zero padding, H' = H. Differentiable.
    """
    if padding not in ("valid", "same"):
        raise ValueError(f"ssim padding must be 'valid' or 'same', got {padding!r}")
    p, _ = _rgb_batch(pred, "pred")
    g_, _ = _rgb_batch(gt, "gt")
    if p.shape != g_.shape:
        raise ValueError(f"ssim: pred {list(p.shape)} and gt {list(g_.shape)} differ")
    if padding == "valid" and min(p.shape[1:3]) < window_size:
        raise ValueError(f"ssim: image {list(p.shape[1:3])} smaller than the {window_size} window")
    x = p.permute(0, 3, 1, 2)
    y = g_.permute(0, 3, 1, 2)
    w = _gauss_window(window_size, sigma, x.dtype, x.device)
    c1 = (k[0] * max_val) ** 2
    c2 = (k[1] * max_val) ** 2
    stats = _blur(torch.cat([x, y, x * x, y * y, x * y], dim=1), w, padding)
    mx, my, sxx, syy, sxy = stats.split(x.shape[1], dim=1)
    vx = sxx - mx * mx
    vy = syy - my * my
    cxy = sxy - mx * my
    s = ((2 * mx * my + c1) * (2 * cxy + c2)) / ((mx * mx + my * my + c1) * (vx + vy + c2))
    return s.mean(dim=1)


def ssim(pred: torch.Tensor, gt: torch.Tensor, mask: Optional[torch.Tensor] = None,
         window_size: int = 11, sigma: float = 1.5, padding: str = "valid",
         max_val: float = 1.0) -> torch.Tensor:
    """Mean SSIM (11x11 Gaussian, sigma 1.5); with ``mask``, the SSIM map averaged
    over the mask (cropped like the map for ``padding='valid'``)."""
    p, single = _rgb_batch(pred, "pred")
    smap = ssim_map(p, gt if gt.ndim == 4 else gt[None], window_size, sigma, padding, max_val)
    if mask is None:
        return _out(smap.mean(dim=(1, 2)), single)
    m = _map_batch(mask, "mask", p)
    if padding == "valid":
        r = window_size // 2
        m = m[:, r: m.shape[1] - r, r: m.shape[2] - r]
    return _out((smap * m).sum(dim=(1, 2)) / m.sum(dim=(1, 2)), single)


def lpips(pred: torch.Tensor, gt: torch.Tensor, model: Optional[LPIPS] = None) -> torch.Tensor:
    """LPIPS-Alex distance of [0,1] RGB images (0-dim or [B]); see :mod:`soma_ros.core.lpips`."""
    return lpips_distance(pred, gt, model)


# ------------------------------------------------------------------ depth metrics
def _depth_valid(pred, gt, mask, robot_mask):
    d, single = _depth_batch(pred, "pred depth")
    t, _ = _depth_batch(gt, "gt depth")
    if d.shape != t.shape:
        raise ValueError(f"depth metrics: pred {list(d.shape)} and gt {list(t.shape)} differ")
    like = t[..., None]
    valid = (t > 0) & torch.isfinite(t)
    m = _map_batch(mask, "mask", like)
    if m is not None:
        valid &= m > 0.5
    r = _map_batch(robot_mask, "robot_mask", like)
    if r is not None:
        valid &= r <= 0.5
    return d, t, valid.to(t.dtype), single


def depth_abs_rel(pred: torch.Tensor, gt: torch.Tensor, mask: Optional[torch.Tensor] = None,
                  robot_mask: Optional[torch.Tensor] = None) -> torch.Tensor:
    """AbsRel ``mean |pred - gt| / gt`` over ``mask & gt > 0 & ~robot_mask`` (NaN if empty)."""
    d, t, v, single = _depth_valid(pred, gt, mask, robot_mask)
    rel = torch.where(v > 0, (d - t).abs() / torch.where(v > 0, t, torch.ones_like(t)), torch.zeros_like(t))
    return _out(rel.sum(dim=(1, 2)) / v.sum(dim=(1, 2)), single)


def depth_rmse(pred: torch.Tensor, gt: torch.Tensor, mask: Optional[torch.Tensor] = None,
               robot_mask: Optional[torch.Tensor] = None) -> torch.Tensor:
    """RMSE ``sqrt(mean (pred - gt)^2)`` (depth units) over the valid pixels (NaN if empty)."""
    d, t, v, single = _depth_valid(pred, gt, mask, robot_mask)
    sq = torch.where(v > 0, (d - t).square(), torch.zeros_like(t))
    return _out(torch.sqrt(sq.sum(dim=(1, 2)) / v.sum(dim=(1, 2))), single)


# ------------------------------------------------------------------ protocol
def apply_eval_masks(pred: torch.Tensor, gt: torch.Tensor, object_mask: torch.Tensor,
                     robot_mask: Optional[torch.Tensor] = None) -> tuple[torch.Tensor, torch.Tensor]:
    """(pred x (1 - robot), gt x object x (1 - robot)); shapes as given."""
    p, single = _rgb_batch(pred, "pred")
    g, _ = _rgb_batch(gt, "gt")
    om = _map_batch(object_mask, "object_mask", p)
    keep = torch.ones_like(om) if robot_mask is None else 1.0 - _map_batch(robot_mask, "robot_mask", p)
    pm = p * keep[..., None]
    gm = g * (om * keep)[..., None]
    return (pm[0], gm[0]) if single else (pm, gm)


def image_metrics(pred: torch.Tensor, gt: torch.Tensor, object_mask: torch.Tensor,
                  robot_mask: Optional[torch.Tensor] = None, with_lpips: bool = True,
                  lpips_model: Optional[LPIPS] = None) -> dict[str, float]:
    """PSNR / SSIM / LPIPS of the protocol (module docstring), means over the batch.

    Also reports ``psnr_masked``: PSNR over the object pixels (object_mask & ~robot).
    """
    with torch.no_grad():
        pm, gm = apply_eval_masks(pred, gt, object_mask, robot_mask)
        p, _ = _rgb_batch(pm, "pred")
        g, _ = _rgb_batch(gm, "gt")
        om = _map_batch(object_mask, "object_mask", p)
        if robot_mask is not None:
            om = om * (1.0 - _map_batch(robot_mask, "robot_mask", p))
        out = {
            "psnr": float(psnr(p, g).mean()),
            "psnr_masked": float(psnr(p, g, mask=om).mean()),
            "ssim": float(ssim(p, g).mean()),
        }
        if with_lpips:
            out["lpips"] = float(lpips(p, g, lpips_model).mean())
    return out


def depth_metrics(pred: torch.Tensor, gt: torch.Tensor, object_mask: torch.Tensor,
                  robot_mask: Optional[torch.Tensor] = None) -> dict[str, float]:
    """AbsRel and RMSE on valid object pixels, means over the batch (NaN images skipped)."""
    with torch.no_grad():
        ar = depth_abs_rel(pred, gt, object_mask, robot_mask).reshape(-1)
        rm = depth_rmse(pred, gt, object_mask, robot_mask).reshape(-1)

        def nanmean(v):
            v = v[torch.isfinite(v)]
            return float(v.mean()) if v.numel() else math.nan

        return {"abs_rel": nanmean(ar), "rmse": nanmean(rm)}


# ------------------------------------------------------------------ training loss
def masked_l2_dssim_loss(pred: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor, lam: float = 0.9,
                         window_size: int = 5, sigma: float = 1.5, dssim_reduce: str = "image",
                         dssim_half: bool = False) -> torch.Tensor:
    """``lam * masked L2 + (1 - lam) * D-SSIM(M x pred, M x gt)`` (paper eq. of L_img).

    * masked L2: ``sum M (pred - gt)^2 / (3 sum M)`` (mean squared error over the
      masked pixels; 0 when the mask is empty);
    * D-SSIM: ``1 - SSIM`` (or ``(1 - SSIM) / 2`` with ``dssim_half``, kornia's
      ``ssim_loss``) of the masked images, Gaussian window ``window_size`` (5),
      sigma 1.5, zero 'same' padding, averaged over the whole image
      (``dssim_reduce='image'``, as the paper's formula) or over the mask (``'mask'``).

    pred, gt: [H,W,3] or [B,H,W,3]; mask [H,W] or [B,H,W] (robot-occluded pixels
    already removed). Returns a scalar, differentiable w.r.t. pred (and gt).
    """
    if not 0.0 <= lam <= 1.0:
        raise ValueError(f"lam must lie in [0, 1], got {lam}")
    if dssim_reduce not in ("image", "mask"):
        raise ValueError(f"dssim_reduce must be 'image' or 'mask', got {dssim_reduce!r}")
    p, _ = _rgb_batch(pred, "pred")
    g, _ = _rgb_batch(gt, "gt")
    if p.shape != g.shape:
        raise ValueError(f"loss: pred {list(p.shape)} and gt {list(g.shape)} differ")
    m = _map_batch(mask, "mask", p)
    msum = m.sum()
    l2 = (m[..., None] * (p - g).square()).sum() / (3.0 * msum.clamp_min(1.0))
    pm = p * m[..., None]
    gm = g * m[..., None]
    smap = ssim_map(pm, gm, window_size, sigma, padding="same")
    if dssim_reduce == "image":
        s = smap.mean()
    else:
        s = (smap * m).sum() / msum.clamp_min(1.0)
    d = 1.0 - s
    if dssim_half:
        d = 0.5 * d
    return lam * l2 + (1.0 - lam) * d
