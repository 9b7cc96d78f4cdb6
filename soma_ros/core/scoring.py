"""Per-frame scoring and aggregation of open-loop rollouts (the numbers of ``soma eval``).

Protocol (paper Sec. "Evaluation Metrics", PhysTwin's masking; the image and
depth primitives are :mod:`soma_ros.core.metrics`):

* **Frames.** Frame 0 is the initial scene every variant starts from (it
  scores the reconstruction, not the dynamics) and is left out; frames
  1..T-1 are scored (:attr:`EvalMetricsConfig.skip_first`).
* **Images** (PSNR, SSIM, LPIPS): the rollout is rendered over a *black*
  background and compared with ``GT x object_mask``, both multiplied by
  ``1 - robot_mask`` (robot-occluded pixels are black in both), over the whole
  image (:func:`soma_ros.core.metrics.image_metrics`). One value per camera
  image; a PSNR of +inf (both images entirely black: nothing to see and nothing
  rendered) is left out of the means and counted in ``n_infinite_psnr``.
* **Depth** (AbsRel, RMSE, metres): the paper's rule, "depth metrics are
  computed on valid object regions; masked-out pixels get the depth of the
  supporting tabletop". Both depth maps are completed with the analytic depth of
  the table plane (:func:`table_depth`, the plane of the scene, infinite): the
  ground truth keeps the measured depth on its object pixels and takes the table
  depth elsewhere; the prediction is the rollout rendered *over the table*,
  ``D + (1 - alpha) * table`` (``D`` the alpha-weighted depth of the splats), so a
  pixel the model leaves empty reads as table, not as 0. The scored region is the
  *measured* object's valid pixels, minus robot-occluded pixels and pixels whose
  ray misses the table plane: the same pixels for every model, so the mean is
  over one fixed set. ``abs_rel_union`` / ``rmse_union`` are also reported: the
  same over the union of the measured and the rendered object (``alpha > 0.5``),
  the rule this harness used first. Its mean is over a region the prediction
  chooses: pixels a model renders onto the table where the object lay, at the
  error of the object's thickness, dilute it. On a held-out rope lift it ranked
  a model that leaves the rope on the table above one whose 3D error is 4x
  smaller (README "Accuracy"), so it is not the headline number; the training
  loss still uses it (it charges splats rendered where there is no object).
* **Chamfer** (metres): between all simulated splat means (not only the visible
  ones: the ground truth holds occluded vertices too) and the ground-truth
  object points of the frame, ``0.5 * (mean_a min_b |a-b| + mean_b min_a |a-b|)``
  (:func:`chamfer_distance`), evaluation only. The ground truth is the reference
  world's simulation mesh (a rope: 25 vertices on its centre line), the splats sit
  on the observed surface, so even a perfect model has a floor of about the
  object's radius / half-thickness; compare variants, not absolute values.
* **Where the depth error lives** (``depth_px_*`` / ``depth_sq_*``, per camera image: the number
  of scored pixels and the sum of their squared depth errors, m^2, in three classes by the
  rendered opacity: ``covered`` alpha > ``pred_mask_alpha``, ``edge`` ``edge_alpha`` < alpha <=
  ``pred_mask_alpha``, ``missed`` alpha <= ``edge_alpha``). On a thin object most of a small
  miss is edge and missed pixels, each costing the object's height above the table;
  :func:`depth_error_shares` turns the means into shares and an RMS per class.
* **Aggregation.** Per episode: the mean over the scored frames (and cameras)
  of each metric (the paper averages "over all frames within each video
  sequence"); per split: the mean over episodes (:func:`aggregate_episodes`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Iterable, Optional, Sequence

import torch

from . import metrics as M
from .cameras import Cameras

__all__ = [
    "METRICS",
    "EXTRA_METRICS",
    "LOWER_IS_BETTER",
    "EvalMetricsConfig",
    "chamfer_distance",
    "table_depth",
    "complete_depth_maps",
    "FrameScores",
    "score_frame",
    "aggregate_frames",
    "aggregate_episodes",
    "COVERAGE_CLASSES",
    "COVERAGE_METRICS",
    "depth_error_shares",
]

#: the columns of the table, in the paper's order, plus the 3D error
METRICS: tuple[str, ...] = ("abs_rel", "rmse", "psnr", "ssim", "lpips", "chamfer")
#: also in metrics.json: depth over the union of measured and rendered object (module docstring)
EXTRA_METRICS: tuple[str, ...] = ("abs_rel_union", "rmse_union")
#: also in metrics.json: the depth error by rendered coverage (module docstring, :func:`depth_error_shares`)
COVERAGE_CLASSES: tuple[str, ...] = ("covered", "edge", "missed")
COVERAGE_METRICS: tuple[str, ...] = tuple(f"depth_{k}_{c}" for c in COVERAGE_CLASSES for k in ("px", "sq"))
LOWER_IS_BETTER = {"abs_rel": True, "rmse": True, "psnr": False, "ssim": False, "lpips": True, "chamfer": True,
                   "abs_rel_union": True, "rmse_union": True}


@dataclass
class EvalMetricsConfig:
    """Scoring options (defaults = the documented protocol)."""

    skip_first: bool = True  # leave frame 0 (the shared initial scene) out
    with_lpips: bool = True
    pred_mask_alpha: float = 0.5  # rendered pixels with alpha above this count as object (depth region)
    edge_alpha: float = 0.05  # the depth error breakdown: alpha <= this is "missed", up to pred_mask_alpha "edge"
    chamfer_chunk: int = 4096  # rows per cdist block (memory bound)

    def validate(self) -> "EvalMetricsConfig":
        if not 0.0 < self.pred_mask_alpha < 1.0:
            raise ValueError(f"pred_mask_alpha must lie in (0, 1), got {self.pred_mask_alpha}")
        if not 0.0 < self.edge_alpha < self.pred_mask_alpha:
            raise ValueError(f"edge_alpha must lie in (0, pred_mask_alpha), got {self.edge_alpha}")
        if self.chamfer_chunk < 1:
            raise ValueError("chamfer_chunk must be >= 1")
        return self


# ------------------------------------------------------------------ 3D
def _nn_dist(a: torch.Tensor, b: torch.Tensor, chunk: int) -> torch.Tensor:
    """For every row of a [N, 3], the distance to its nearest row of b [M, 3] -> [N]."""
    out = []
    for i in range(0, a.shape[0], chunk):
        out.append(torch.cdist(a[i: i + chunk], b).min(dim=1).values)
    return torch.cat(out)


def chamfer_distance(a: torch.Tensor, b: torch.Tensor, chunk: int = 4096) -> float:
    """Symmetric Chamfer distance ``0.5 * (mean_i min_j |a_i - b_j| + mean_j min_i |a_i - b_j|)``.

    a [N, 3], b [M, 3] (metres, same frame); N, M >= 1. Distances, not squared distances.
    Computed in float64.
    """
    if a.ndim != 2 or a.shape[1] != 3 or b.ndim != 2 or b.shape[1] != 3:
        raise ValueError(f"chamfer_distance: need [N, 3] and [M, 3], got {list(a.shape)} and {list(b.shape)}")
    if a.shape[0] == 0 or b.shape[0] == 0:
        raise ValueError("chamfer_distance: empty point set")
    a64 = a.detach().to(torch.float64)
    b64 = b.detach().to(device=a64.device, dtype=torch.float64)
    d_ab = _nn_dist(a64, b64, chunk).mean()
    d_ba = _nn_dist(b64, a64, chunk).mean()
    return float(0.5 * (d_ab + d_ba))


# ------------------------------------------------------------------ depth
def table_depth(cameras: Cameras, plane_normal: torch.Tensor, plane_offset: float) -> torch.Tensor:
    """Camera-z depth of the plane ``{x : n.x + d = 0}`` at every pixel centre: [C, H, W] (metres).

    0 where the pixel ray does not hit the plane in front of the camera. Pixel (col, row)
    centre at (col + 0.5, row + 0.5), OpenCV optical frame (z forward): the ray through it is
    ``K^-1 [u, v, 1]`` (z = 1), so the ray parameter at the hit is the camera-z depth.
    """
    dt = torch.float64
    K = cameras.K.to(dt)
    c2w = cameras.cam_to_world().to(dt)
    n = torch.as_tensor(plane_normal, dtype=dt, device=K.device).reshape(3)
    n = n / n.norm()
    d = float(plane_offset)
    H, W = cameras.height, cameras.width
    v, u = torch.meshgrid(torch.arange(H, dtype=dt, device=K.device) + 0.5,
                          torch.arange(W, dtype=dt, device=K.device) + 0.5, indexing="ij")
    pix = torch.stack([u, v, torch.ones_like(u)], dim=-1)  # [H, W, 3]
    rays_cam = torch.einsum("cij,hwj->chwi", torch.linalg.inv(K), pix)  # z = 1
    rays_w = torch.einsum("cij,chwj->chwi", c2w[:, :3, :3], rays_cam)
    o = c2w[:, :3, 3]  # [C, 3]
    num = -(o @ n + d)  # [C]
    den = rays_w @ n  # [C, H, W]
    safe = torch.where(den.abs() > 1e-12, den, torch.ones_like(den))
    t = num[:, None, None] / safe
    hit = (den.abs() > 1e-12) & (t > 0)
    out = torch.where(hit, t, torch.zeros_like(t))
    assert out.shape == (len(cameras), H, W)
    return out.to(torch.float32)


def complete_depth_maps(
    pred_depth: torch.Tensor,
    pred_alpha: torch.Tensor,
    gt_depth: torch.Tensor,
    object_mask: torch.Tensor,
    robot_mask: Optional[torch.Tensor],
    table: torch.Tensor,
    pred_mask_alpha: float = 0.5,
    region: str = "union",
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The paper's table-completed depth maps and a region (see module docstring).

    All inputs [C, H, W] (masks bool); ``pred_depth`` is the renderer's expected depth (0 where
    nothing was rendered), ``pred_alpha`` its accumulated opacity. Returns (pred, gt, region)
    [C, H, W]: pred = ``pred_depth * alpha + (1 - alpha) * table``; gt = measured depth on valid
    object pixels, table elsewhere; region ``"measured"`` = ``object & gt valid & ~robot &
    table > 0`` (the evaluation's), ``"union"`` = ``(object & gt valid | alpha >
    pred_mask_alpha) & ~robot & table > 0`` (the training loss's ``scored`` region).
    """
    if region not in ("measured", "union"):
        raise ValueError(f"complete_depth_maps: region must be 'measured' or 'union', got {region!r}")
    shape = gt_depth.shape
    for name, t in (("pred_depth", pred_depth), ("pred_alpha", pred_alpha), ("object_mask", object_mask), ("table", table)):
        if t.shape != shape:
            raise ValueError(f"complete_depth_maps: {name} is {list(t.shape)}, gt_depth {list(shape)}")
    if robot_mask is not None and robot_mask.shape != shape:
        raise ValueError(f"complete_depth_maps: robot_mask is {list(robot_mask.shape)}, gt_depth {list(shape)}")
    a = pred_alpha.clamp(0.0, 1.0).to(torch.float32)
    tbl = table.to(torch.float32)
    pred = pred_depth.to(torch.float32) * a + (1.0 - a) * tbl
    obj = object_mask.bool() & (gt_depth > 0) & torch.isfinite(gt_depth)
    gt = torch.where(obj, gt_depth.to(torch.float32), tbl)
    keep = (obj | (a > pred_mask_alpha)) if region == "union" else obj
    keep = keep & (tbl > 0)
    if robot_mask is not None:
        keep &= ~robot_mask.bool()
    return pred, gt, keep


# ------------------------------------------------------------------ one frame
@dataclass
class FrameScores:
    """Scores of one frame: one entry per camera (NaN where a metric is undefined)."""

    frame: int
    per_camera: dict[str, dict[str, float]] = field(default_factory=dict)
    chamfer: float = math.nan

    def camera_values(self, metric: str) -> list[float]:
        return [v[metric] for v in self.per_camera.values() if metric in v]


def score_frame(
    frame: int,
    pred_rgb: torch.Tensor,
    pred_depth: torch.Tensor,
    pred_alpha: torch.Tensor,
    gt_rgb: torch.Tensor,
    gt_depth: torch.Tensor,
    object_mask: torch.Tensor,
    robot_mask: Optional[torch.Tensor],
    table: torch.Tensor,
    camera_names: Sequence[str],
    pred_points: Optional[torch.Tensor] = None,
    gt_points: Optional[torch.Tensor] = None,
    cfg: Optional[EvalMetricsConfig] = None,
    lpips_model=None,
) -> FrameScores:
    """Score one frame of C cameras.

    pred_rgb [C, H, W, 3] rendered over black, pred_depth / pred_alpha [C, H, W];
    gt_rgb [C, H, W, 3] in [0, 1], gt_depth [C, H, W] metres (0 = invalid), object_mask and
    robot_mask [C, H, W] bool, table [C, H, W] (:func:`table_depth`); pred_points [N, 3] and
    gt_points [M, 3] in one frame for the Chamfer distance (skipped if either is None).
    """
    cfg = cfg or EvalMetricsConfig()
    C, H, W = gt_depth.shape
    if pred_rgb.shape != (C, H, W, 3) or gt_rgb.shape != (C, H, W, 3):
        raise ValueError(f"score_frame: rgb must be [{C}, {H}, {W}, 3], got {list(pred_rgb.shape)} and {list(gt_rgb.shape)}")
    if len(camera_names) != C:
        raise ValueError(f"score_frame: {len(camera_names)} camera names for {C} cameras")
    out = FrameScores(frame=frame)
    with torch.no_grad():
        pd, gd, region = complete_depth_maps(pred_depth, pred_alpha, gt_depth, object_mask, robot_mask, table,
                                             cfg.pred_mask_alpha, region="measured")
        ar = M.depth_abs_rel(pd, gd, region).reshape(-1)
        rm = M.depth_rmse(pd, gd, region).reshape(-1)
        _, _, union = complete_depth_maps(pred_depth, pred_alpha, gt_depth, object_mask, robot_mask, table,
                                          cfg.pred_mask_alpha, region="union")
        ar_u = M.depth_abs_rel(pd, gd, union).reshape(-1)
        rm_u = M.depth_rmse(pd, gd, union).reshape(-1)
        a = pred_alpha.clamp(0.0, 1.0)
        sq = (pd - gd).square()
        coverage = {}
        for cls, sel in zip(COVERAGE_CLASSES, (a > cfg.pred_mask_alpha, (a > cfg.edge_alpha) & (a <= cfg.pred_mask_alpha),
                                               a <= cfg.edge_alpha)):
            sel = sel & region
            coverage[f"depth_px_{cls}"] = sel.sum(dim=(1, 2)).double()
            coverage[f"depth_sq_{cls}"] = torch.where(sel, sq, torch.zeros_like(sq)).sum(dim=(1, 2)).double()
        # the protocol of M.image_metrics, batched over the cameras (one value per camera)
        pm, gm = M.apply_eval_masks(pred_rgb.float(), gt_rgb.float(), object_mask, robot_mask)
        ps = M.psnr(pm, gm).reshape(-1)
        ss = M.ssim(pm, gm).reshape(-1)
        lp = M.lpips(pm, gm, lpips_model).reshape(-1) if cfg.with_lpips else None
        for c, name in enumerate(camera_names):
            row = {"psnr": float(ps[c]), "ssim": float(ss[c]), "abs_rel": float(ar[c]), "rmse": float(rm[c]),
                   "abs_rel_union": float(ar_u[c]), "rmse_union": float(rm_u[c]),
                   **{k: float(v[c]) for k, v in coverage.items()}}
            if lp is not None:
                row["lpips"] = float(lp[c])
            row["depth_pixels"] = float(region[c].sum())
            row["depth_pixels_union"] = float(union[c].sum())
            out.per_camera[name] = row
        if pred_points is not None and gt_points is not None:
            out.chamfer = chamfer_distance(pred_points, gt_points, cfg.chamfer_chunk)
    return out


# ------------------------------------------------------------------ aggregation
def _mean_finite(values: Iterable[float]) -> tuple[float, int, int]:
    """(mean of the finite values or NaN, number used, number left out)."""
    vals = list(values)
    fin = [v for v in vals if isinstance(v, (int, float)) and math.isfinite(v)]
    return (sum(fin) / len(fin) if fin else math.nan), len(fin), len(vals) - len(fin)


def aggregate_frames(frames: Sequence[FrameScores],
                     metrics: Sequence[str] = METRICS + EXTRA_METRICS + COVERAGE_METRICS) -> dict:
    """Episode summary: the mean of every metric over the scored frames and cameras.

    Returns {metric: mean} plus ``per_camera`` {camera: {metric: mean}}, ``frames`` (count),
    ``n_infinite_psnr`` and ``n_undefined`` {metric: values left out (NaN / inf)}.
    """
    if not frames:
        raise ValueError("aggregate_frames: no frames")
    out: dict = {}
    undefined: dict[str, int] = {}
    cams = list(frames[0].per_camera)
    for m in metrics:
        if m == "chamfer":
            vals = [f.chamfer for f in frames]
        else:
            vals = [v for f in frames for v in f.camera_values(m)]
        if not vals:
            continue
        mean, _, left = _mean_finite(vals)
        out[m] = mean
        undefined[m] = left
    out["n_infinite_psnr"] = sum(1 for f in frames for v in f.camera_values("psnr") if v == math.inf)
    out["per_camera"] = {
        c: {m: _mean_finite(f.per_camera[c][m] for f in frames if c in f.per_camera)[0]
            for m in metrics if m != "chamfer" and m in frames[0].per_camera.get(c, {})}
        for c in cams
    }
    out["frames"] = len(frames)
    out["n_undefined"] = undefined
    return out


def aggregate_episodes(episodes: dict[str, dict],
                       metrics: Sequence[str] = METRICS + EXTRA_METRICS + COVERAGE_METRICS) -> dict:
    """Split summary: the mean over episodes of each per-episode mean ({metric: value}, NaN-safe),
    plus ``episodes`` (count)."""
    if not episodes:
        raise ValueError("aggregate_episodes: no episodes")
    out: dict = {}
    for m in metrics:
        vals = [e[m] for e in episodes.values() if m in e]
        if vals:
            out[m] = _mean_finite(vals)[0]
    out["episodes"] = len(episodes)
    return out


def depth_error_shares(mean: dict) -> dict[str, dict[str, float]]:
    """{class: {"pixels": share of the scored pixels, "error": share of the squared depth error,
    "rms": m}} for ``covered``, ``edge``, ``missed`` (module docstring) from a summary's means of
    ``depth_px_*`` / ``depth_sq_*`` (:func:`aggregate_frames`, :func:`aggregate_episodes`). The
    shares are of the means (every camera image and, across episodes, every episode weighted
    alike), so they sum to 1; empty where the summary has no such keys."""
    px = {c: mean.get(f"depth_px_{c}") for c in COVERAGE_CLASSES}
    sq = {c: mean.get(f"depth_sq_{c}") for c in COVERAGE_CLASSES}
    if any(v is None or not math.isfinite(v) for v in list(px.values()) + list(sq.values())):
        return {}
    tp, ts = sum(px.values()), sum(sq.values())
    return {c: {"pixels": px[c] / tp if tp > 0 else math.nan, "error": sq[c] / ts if ts > 0 else math.nan,
                "rms": math.sqrt(sq[c] / px[c]) if px[c] > 0 else math.nan} for c in COVERAGE_CLASSES}
