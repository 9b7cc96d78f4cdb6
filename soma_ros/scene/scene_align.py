"""Register a user's splat scan (.ply / .splat, any frame and scale) to a rig by Sim(3).

A team's own 3DGS tool writes its scan in its own frame: recentred, rotated, perhaps
scaled. :func:`align_scan` finds ``x_rig = s R x_scan + t`` in three stages:

1. **Coarse** (:func:`coarse_hypotheses`): centroids matched, scale = ratio of the RMS
   radii, rotations from the principal axes of both clouds (the four sign choices with
   det +1, each also turned about the target's least-spread axis by ``yaw_steps`` angles,
   which covers flat or nearly symmetric objects whose axes are ill-defined).
2. **ICP with scale** (:func:`icp_sim3`) from every hypothesis: each target point is matched
   to its nearest transformed scan splat (the target is a partial view of the surface, the
   scan the whole object, so correspondences run target -> scan), pairs beyond
   ``max(trim_distance, median)`` are dropped, and Umeyama's closed form (with scale) is
   solved; the hypothesis with the lowest trimmed RMS wins.
3. **Photometric refinement** (:func:`photometric_refine`, when views are given): a small
   Sim(3) correction (rotation vector, translation, log-scale) and a per-channel colour gain
   and offset (the scan's tool and the rig's cameras do not share exposure and white balance)
   fitted for a few dozen iterations to the object pixels of the views (L1 + an alpha term)
   with the public renderer (learning rates decayed tenfold over the iterations). The
   correction is kept only if it lowers the loss over all views.

The target is the rig's object points: a capture's ``pcd.ply``, its masked depth, or the
visual hull of its masks; for a bag, the fused masked depth of the first frame(s). The
residual reported is the distance from every target point to the nearest aligned splat
centre (RMS and median, millimetres), over all target points and over the inliers.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Optional

import numpy as np
import torch

from soma_ros.core.calibration import Sim3, umeyama
from soma_ros.core.geometry import quat_multiply, quat_normalize, rotmat_to_quat
from soma_ros.core.splats import Splats

__all__ = ["AlignConfig", "AlignResult", "coarse_hypotheses", "icp_sim3", "transform_splats", "align_scan",
           "photometric_refine", "residual_mm"]


@dataclass
class AlignConfig:
    """Settings of :func:`align_scan`; distances in metres of the target frame."""

    yaw_steps: int = 8
    icp_iters: int = 40
    trim_distance: float = 0.01
    max_points: int = 20000
    photometric_iters: int = 150
    lr_rotation: float = 5e-3  # rad per Adam step, decayed 10x over the refinement
    lr_translation: float = 3e-3  # m per Adam step, decayed likewise
    lr_scale: float = 2e-3
    lr_colour: float = 1e-2
    alpha_weight: float = 0.1
    crop_margin: int = 16
    seed: int = 0

    def validate(self) -> "AlignConfig":
        if self.yaw_steps < 1 or self.icp_iters < 1 or self.max_points < 10 or self.photometric_iters < 0:
            raise ValueError("align config: yaw_steps, icp_iters >= 1, max_points >= 10, photometric_iters >= 0")
        if not self.trim_distance > 0:
            raise ValueError(f"align config: trim_distance must be > 0, got {self.trim_distance}")
        return self


@dataclass
class AlignResult:
    sim3: Sim3  # scan -> rig
    splats: Splats  # the scan in the rig frame (colours corrected when refined)
    info: dict = field(default_factory=dict)


def _rot_about(axis: np.ndarray, angle: float) -> np.ndarray:
    a = axis / np.linalg.norm(axis)
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + math.sin(angle) * K + (1 - math.cos(angle)) * K @ K


def _subsample(x: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
    return x if len(x) <= n else x[rng.choice(len(x), n, replace=False)]


def coarse_hypotheses(src: np.ndarray, dst: np.ndarray, yaw_steps: int = 8) -> list[Sim3]:
    """Initial Sim(3)s (dst ~ s R src + t) from centroids, RMS radii and principal axes."""
    cs, cd = src.mean(0), dst.mean(0)
    rs = math.sqrt(((src - cs) ** 2).sum(1).mean())
    rd = math.sqrt(((dst - cd) ** 2).sum(1).mean())
    if rs < 1e-12 or rd < 1e-12:
        raise ValueError("scene align: a point set has no extent")
    s = rd / rs
    _, Vs = np.linalg.eigh(np.cov((src - cs).T))  # columns: axes, ascending spread
    _, Vd = np.linalg.eigh(np.cov((dst - cd).T))
    out = []
    for sx in (1, -1):
        for sy in (1, -1):
            D = np.diag([sx, sy, 1.0])
            R0 = Vd @ D @ Vs.T
            if np.linalg.det(R0) < 0:
                R0 = Vd @ np.diag([sx, sy, -1.0]) @ Vs.T
            for k in range(yaw_steps):
                R = _rot_about(Vd[:, 0], 2 * math.pi * k / yaw_steps) @ R0
                out.append(Sim3(s, R, cd - s * R @ cs))
    return out


def icp_sim3(src: np.ndarray, dst: np.ndarray, init: Sim3, iters: int = 40, trim: float = 0.01) -> tuple[Sim3, float]:
    """Trimmed ICP with scale: returns (Sim3 with dst ~ s R src + t, trimmed RMS distance of dst
    to the transformed src)."""
    from scipy.spatial import cKDTree

    T = init
    err = float("inf")
    for _ in range(iters):
        moved = T.apply_points(src)
        d, j = cKDTree(moved).query(dst)
        thr = max(trim, float(np.median(d)))
        keep = d <= thr
        if keep.sum() < 4:
            break
        err = math.sqrt(float((d[keep] ** 2).mean()))
        try:
            new = umeyama(src[j[keep]], dst[keep], with_scale=True)
        except ValueError:
            break
        step = np.abs(new.matrix() - T.matrix()).max()
        T = new
        if step < 1e-9:
            break
    moved = T.apply_points(src)
    d, _ = cKDTree(moved).query(dst)
    keep = d <= max(trim, float(np.median(d)))
    return T, math.sqrt(float((d[keep] ** 2).mean()))


def transform_splats(splats: Splats, T: Sim3) -> Splats:
    """Splats moved by the similarity T (means s R x + t, orientations R q, scales s x)."""
    dt = splats.means.dtype
    R = torch.as_tensor(T.R, dtype=torch.float64)
    means = (splats.means.double() @ R.T * T.s + torch.as_tensor(T.t, dtype=torch.float64)).to(dt)
    q = quat_normalize(quat_multiply(rotmat_to_quat(R)[None].expand(len(splats), 4), splats.quats.double())).to(dt)
    return Splats(means=means, quats=q, scales=splats.scales * T.s, opacities=splats.opacities.clone(),
                  sh_dc=splats.sh_dc.clone(), sh_rest=splats.sh_rest.clone(), mass=splats.mass.clone(),
                  attrs=splats.attrs.clone())


def residual_mm(splats: Splats, target: np.ndarray, trim: float) -> dict:
    """Distances target point -> nearest splat centre, in mm: RMS and median over all points and
    the RMS over the inliers (distance <= ``trim``)."""
    from scipy.spatial import cKDTree

    d, _ = cKDTree(splats.means.detach().double().numpy()).query(target)
    inl = d <= trim
    return {"rms_mm": 1000 * math.sqrt(float((d ** 2).mean())), "median_mm": 1000 * float(np.median(d)),
            "inlier_rms_mm": 1000 * math.sqrt(float((d[inl] ** 2).mean())) if inl.any() else float("nan"),
            "inlier_fraction": float(inl.mean()), "target_points": int(len(target))}


def _skew_exp(w: torch.Tensor) -> torch.Tensor:
    """Rotation vector [3] -> rotation matrix [3, 3] (Rodrigues, differentiable, safe at 0)."""
    th2 = (w * w).sum()
    th = torch.sqrt(th2 + 1e-24)
    a = torch.where(th2 > 1e-12, torch.sin(th) / th, 1 - th2 / 6)
    b = torch.where(th2 > 1e-12, (1 - torch.cos(th)) / th2.clamp_min(1e-24), 0.5 - th2 / 24)
    z = torch.zeros((), dtype=w.dtype)
    K = torch.stack([torch.stack([z, -w[2], w[1]]), torch.stack([w[2], z, -w[0]]), torch.stack([-w[1], w[0], z])])
    return torch.eye(3, dtype=w.dtype) + a * K + b * (K @ K)


@torch.enable_grad()
def photometric_refine(splats: Splats, views, cfg: AlignConfig, progress: bool = False) -> tuple[Splats, Sim3, dict]:
    """A small Sim(3) about the splats' centroid and a per-channel colour gain / offset, fitted to
    the object pixels of ``views`` (:class:`soma_ros.scene.capture.CaptureViews`). Returns (refined
    splats, the correction as a Sim3 in the splats' frame, info with the loss before and after)."""
    from tqdm import tqdm

    from soma_ros.core.geometry import covariance_from_scale_rot
    from soma_ros.core.render import render

    from soma_ros.scene.splat_fit import crop_views

    crops = crop_views(views, cfg.crop_margin)
    c = splats.means.detach().double().mean(0)
    x = (splats.means.detach().double() - c).float()
    cov0 = covariance_from_scale_rot(splats.scales.detach().float(), quat_normalize(splats.quats.detach().float()))
    rgb0 = splats.colors().detach().float()
    op = splats.opacities.detach().float()
    w = torch.zeros(3, requires_grad=True)
    t = torch.zeros(3, requires_grad=True)
    ls = torch.zeros(1, requires_grad=True)
    gain = torch.zeros(3, requires_grad=True)  # log gain
    bias = torch.zeros(3, requires_grad=True)
    opt = torch.optim.Adam([{"params": [w], "lr": cfg.lr_rotation}, {"params": [t], "lr": cfg.lr_translation},
                            {"params": [ls], "lr": cfg.lr_scale}, {"params": [gain, bias], "lr": cfg.lr_colour}])

    def loss_all(views_idx=None) -> torch.Tensor:
        R = _skew_exp(w)
        s = ls.exp()
        means = (x @ R.T) * s + (c.float() + t)
        covs = (R @ cov0 @ R.T) * s * s
        col = (rgb0 * gain.exp() + bias).clamp(0, 1)
        tot = 0.0
        for vc in (crops if views_idx is None else [crops[i] for i in views_idx]):
            out = render(means, covs, col, op, vc.camera)
            fm = vc.mask.float()
            l1 = ((out.rgb[0] - vc.gt).abs().sum(-1) * fm).sum() / (3 * fm.sum().clamp_min(1))
            a = ((out.alpha[0] - fm) ** 2).mean()
            tot = tot + l1 + cfg.alpha_weight * a
        return tot / (len(crops) if views_idx is None else len(views_idx))

    with torch.no_grad():
        before = float(loss_all())
    g = torch.Generator().manual_seed(cfg.seed)
    sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda k: 0.1 ** (k / max(1, cfg.photometric_iters)))
    for _ in tqdm(range(cfg.photometric_iters), desc="align: photometric", disable=not progress, unit="it"):
        i = int(torch.randint(len(crops), (1,), generator=g))
        loss = loss_all([i])
        opt.zero_grad()
        loss.backward()
        opt.step()
        sched.step()
    with torch.no_grad():
        after = float(loss_all())
    info = {"loss_before": before, "loss_after": after, "iters": cfg.photometric_iters}
    if not after < before:
        info["kept"] = False
        return splats, Sim3.identity(), info
    with torch.no_grad():
        R = _skew_exp(w.detach().double()).numpy()
        s = float(ls.detach().exp())
        cn = c.numpy()
        corr = Sim3(s, R, cn + t.detach().double().numpy() - s * R @ cn)
        moved = transform_splats(splats, corr)
        from soma_ros.core.splats import SH_C0

        # colour' = gain colour + offset, exact on the SH coefficients (before clamping)
        k = gain.detach().exp().to(moved.sh_dc.dtype)
        dc = (k * (0.5 + SH_C0 * moved.sh_dc) + bias.detach().to(moved.sh_dc.dtype) - 0.5) / SH_C0
        moved = Splats(moved.means, moved.quats, moved.scales, moved.opacities, dc, moved.sh_rest * k, moved.mass,
                       moved.attrs)
    info.update({"kept": True, "colour_gain": gain.detach().exp().tolist(), "colour_offset": bias.detach().tolist(),
                 "rotation_deg": math.degrees(float(w.detach().norm())), "translation_mm": 1000 * float(t.detach().norm()),
                 "scale": s})
    return moved, corr, info


def align_scan(scan: Splats, target: np.ndarray, cfg: Optional[AlignConfig] = None, views=None,
               progress: bool = False) -> AlignResult:
    """The Sim(3) scan -> rig that puts ``scan`` onto the rig's object points ``target`` [M, 3]
    (see the module docstring); ``views`` (CaptureViews of the rig) enable the photometric stage."""
    cfg = (cfg or AlignConfig()).validate()
    target = np.asarray(target, dtype=np.float64)
    if target.ndim != 2 or target.shape[1] != 3 or len(target) < 10:
        raise ValueError(f"scene align: need at least 10 target points [M, 3], got {list(target.shape)}")
    if len(scan) < 10:
        raise ValueError(f"scene align: the scan has only {len(scan)} splats")
    rng = np.random.default_rng(cfg.seed)
    src = _subsample(scan.means.detach().double().numpy(), cfg.max_points, rng)
    dst = _subsample(target, cfg.max_points, rng)
    hyps = coarse_hypotheses(src, dst, cfg.yaw_steps)
    best = None
    trim = cfg.trim_distance
    for h in hyps:
        T, err = icp_sim3(src, dst, h, cfg.icp_iters, trim)
        if best is None or err < best[1]:
            best = (T, err)
    T, err = best
    moved = transform_splats(scan, T)
    info = {"hypotheses": len(hyps), "icp_trimmed_rms_mm": 1000 * err, "icp": residual_mm(moved, target, trim)}
    if views is not None and cfg.photometric_iters > 0:
        moved, corr, pinfo = photometric_refine(moved, views, cfg, progress)
        T = corr @ T
        info["photometric"] = pinfo
    info["residual"] = residual_mm(moved, target, trim)
    info["sim3"] = T.to_dict()
    return AlignResult(T, moved, info)


# ------------------------------------------------------------------ captures, bags, bundles
def capture_target_points(views) -> tuple[np.ndarray, str]:
    """The rig's object points of a capture and where they come from: its ``pcd.ply``, else its
    masked depth back-projected, else the visual hull of its masks."""
    if views.points is not None and len(views.points) >= 10:
        return views.points.double().numpy(), "pcd.ply"
    if views.depth is not None:
        from soma_ros.data.dataset import backproject

        c2w = views.cameras.cam_to_world().double()
        pts = [backproject(views.depth[v], views.cameras.K[v].double(), c2w[v], views.masks[v] & (views.depth[v] > 0))[0]
               for v in range(views.num_views)]
        pts = torch.cat([p for p in pts if len(p)]) if any(len(p) for p in pts) else torch.zeros(0, 3)
        if len(pts) >= 10:
            return pts.double().numpy(), "masked depth"
    from soma_ros.scene.capture import initial_splats_from_capture

    hull = initial_splats_from_capture(views, list(range(views.num_views)), init_scale=1e-3).means
    return hull.double().numpy(), "visual hull of the masks"


def _table_from_capture(splats: Splats, views, g: float = 9.81) -> tuple[np.ndarray, float, np.ndarray, str]:
    """(normal against gravity, offset, gravity, method) for a capture: a RANSAC plane of the
    non-object depth when the capture has depth, else the least-spread axis of the object
    (a flat object lying on the table); the sign by the cameras (paper's rule)."""
    from soma_ros.core.calibration import fit_table_plane, gravity_from_camera

    x = splats.means.detach().double().numpy()
    n = None
    method = "object's least-spread axis (the capture has no depth)"
    if views.depth is not None:
        from soma_ros.data.dataset import backproject

        c2w = views.cameras.cam_to_world().double()
        pts = [backproject(views.depth[v], views.cameras.K[v].double(), c2w[v],
                           ~views.masks[v] & (views.depth[v] > 0))[0].numpy() for v in range(views.num_views)]
        bg = np.concatenate(pts)
        bg = bg[np.linalg.norm(bg - x.mean(0), axis=1) < 0.4]
        if len(bg) >= 50:
            n, _ = fit_table_plane(bg, iters=400, threshold=0.004)
            method = "RANSAC plane of the non-object depth"
    if n is None:
        _, V = np.linalg.eigh(np.cov((x - x.mean(0)).T))
        n = V[:, 0]
    votes = []
    c2w = views.cameras.cam_to_world().double().numpy()
    for v in range(views.num_views):
        try:
            votes.append(gravity_from_camera(n, c2w[v]))
        except ValueError:
            continue
    if not votes:
        raise ValueError("scene align: every camera views the table edge-on; the gravity sign is undetermined")
    g_dir = votes[0]
    normal = -g_dir
    h = x @ normal
    offset = -float(np.percentile(h, 1.0))  # the object rests on the plane
    return normal, offset, g * g_dir, method


def _write_bundle(out, splats: Splats, object_name: str, robot: str, views, dt: float, extra: dict):
    from soma_ros.core.config import load_model_config, load_object_config
    from soma_ros.core.hierarchy import build_hierarchy
    from soma_ros.core.scene_bundle import CameraSpec, SceneBundle

    from soma_ros.scene.files import save_scene

    obj = load_object_config(object_name)
    mc = load_model_config("cpu", object=obj)  # the default model's hierarchy for this object
    sp = Splats(splats.means.float(), splats.quats.float(), splats.scales.float(), splats.opacities.float(),
                splats.sh_dc.float(), splats.sh_rest.float(), splats.means.new_full((len(splats),), obj.total_mass / len(splats)).float())
    normal, offset, grav, method = _table_from_capture(sp, views)
    hier = build_hierarchy(sp.means, sp.mass, mc.hierarchy.thresholds, mc.hierarchy.seed_fraction)
    c2w = views.cameras.cam_to_world().double().numpy()
    names = views.cameras.names or [f"view_{i}" for i in range(views.num_views)]
    cams = [CameraSpec(names[i], views.cameras.width, views.cameras.height, views.cameras.K[i].double().numpy(),
                       cam_to_sim=c2w[i]) for i in range(views.num_views)]
    bundle = SceneBundle(splats=sp, gravity=grav, table_normal=normal, table_offset=offset, dt=float(dt),
                         object_name=obj.name, robot_config=robot, cameras=cams,
                         extra={**extra, "table_from": method, "hierarchy_sizes": hier.sizes})
    save_scene(out, bundle, hier, None)
    return bundle, hier, method


def _report_views(out, splats: Splats, views, before: Optional[Splats], with_lpips: bool = True) -> list[dict]:
    from soma_ros.scene.recon_report import contact_sheet, render_views, view_metrics

    ren, alpha = render_views(splats, views, with_alpha=True)
    rows = view_metrics(ren, views, with_lpips=with_lpips, alphas=alpha)
    if before is not None:
        ren0 = render_views(before, views)
        for r, r0 in zip(rows, view_metrics(ren0, views, with_lpips=False)):
            r["psnr_masked_geometric_only"] = r0["psnr_masked"]
    contact_sheet(out / "align_compare.png", ren, views)
    return rows


def align_to_capture(file, capture, out, cfg: Optional[AlignConfig] = None, object_name: str = "rope",
                     robot: str = "panda", dt: float = 1 / 30, progress: bool = True,
                     holdout_view: Optional[int] = None) -> dict:
    """`soma scene align --capture`: align the scan to the capture, write the scene bundle into OUT
    (splats.ply, scene.json, hierarchy.pt) plus align.json and align_compare.png.

    ``holdout_view``: the photometric stage fits the other views only, and the report scores that
    view as held out (``role``, ``psnr_holdout``), as ``soma reconstruct --holdout-view`` does.
    The geometric stage registers to the capture's point cloud (``pcd.ply``, which a capture
    fuses from its cameras) when there is one, else to the other views' masked depth or visual
    hull; no pixel of the held-out view is fitted. The table plane of the written bundle is
    still found from every view."""
    import json
    import time
    from pathlib import Path

    from soma_ros.core.ply import load_splats

    from soma_ros.scene.capture import read_capture

    t0 = time.time()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    cfg = (cfg or AlignConfig()).validate()
    views = read_capture(capture)
    if holdout_view is not None and not 0 <= holdout_view < views.num_views:
        raise ValueError(f"scene align: --holdout-view {holdout_view} is not a view of {capture} "
                         f"(0..{views.num_views - 1})")
    fit_idx = [i for i in range(views.num_views) if i != holdout_view]
    scan = load_splats(file)
    scan.validate()
    fit_views = views.select(fit_idx)
    target, source = capture_target_points(fit_views)
    geo = align_scan(scan, target, cfg)
    res = geo
    if cfg.photometric_iters > 0:
        moved, corr, pinfo = photometric_refine(geo.splats, fit_views, cfg, progress)
        pinfo["views"] = fit_idx
        res = AlignResult(corr @ geo.sim3, moved, {**geo.info, "photometric": pinfo,
                                                   "residual": residual_mm(moved, target, cfg.trim_distance)})
    _write_bundle(out, res.splats, object_name, robot, views, dt,
                  {"source_scan": str(file), "source_capture": str(capture), "scan_to_sim": res.sim3.to_dict()})
    rows = _report_views(out, res.splats, views, geo.splats if res is not geo else None)
    for i, r in enumerate(rows):
        r["role"] = "holdout" if i == holdout_view else "fit"
    report = {"scan": str(file), "capture": str(capture), "out": str(out), "splats": len(res.splats),
              "target": source, "target_points": int(len(target)), "sim3": res.sim3.to_dict(),
              "scale": res.sim3.s, "residual": res.info["residual"], "residual_geometric": geo.info["residual"],
              "photometric": res.info.get("photometric"), "views": rows,
              "min_psnr_masked": min(r["psnr_masked"] for r in rows), "seconds": round(time.time() - t0, 1)}
    if holdout_view is not None:
        report.update({"holdout_view": holdout_view, "psnr_holdout": rows[holdout_view]["psnr_masked"]})
    (out / "align.json").write_text(json.dumps(report, indent=2))
    return report


def align_to_bag(file, bag, out, cfg: Optional[AlignConfig] = None, object_name: str = "rope", robot: str = "panda",
                 config=None, progress: bool = True) -> dict:
    """`soma scene align --bag`: align the scan to the bag's fused masked depth of its set-up frames
    (and refine against those frames' views), then the bag's scene set-up (table, gravity,
    robot -> sim, hierarchy) with the aligned scan as G_0; writes the bundle, align.json and
    align_compare.png into OUT."""
    import json
    import time
    from pathlib import Path

    from soma_ros.core.config import load_model_config, load_object_config
    from soma_ros.core.ply import load_splats
    from soma_ros.core.robot import RobotModel

    from soma_ros.data.dataset import prepare_episode
    from soma_ros.scene.scene_setup import episode_views, setup_scene
    from soma_ros.scene.files import save_scene

    t0 = time.time()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    cfg = (cfg or AlignConfig()).validate()
    if config is None:
        raise ValueError("align_to_bag needs the training config whose data and scene sections it follows")
    tc = config
    rm = RobotModel.from_config(robot, dtype=torch.float64)
    obj = load_object_config(object_name)
    mc = load_model_config(tc.model, object=obj)
    ep = prepare_episode(Path(bag), rm, tc.data)
    frames = [f for f in tc.scene.frames if f < ep.num_frames]
    if not frames:
        raise ValueError(f"scene.frames {tc.scene.frames} are all beyond the bag's {ep.num_frames} frames")
    target, _ = ep.object_points(frames, erode_px=tc.scene.erode_px)
    scan = load_splats(file)
    scan.validate()
    views = episode_views(ep, frames)
    res = align_scan(scan, target.double().numpy(), cfg, views=views if cfg.photometric_iters > 0 else None,
                     progress=progress)
    setup = setup_scene(ep, tc.scene, obj.name, robot, obj.total_mass, mc.hierarchy.thresholds,
                        mc.hierarchy.seed_fraction, init_splats=res.splats, progress=progress)
    setup.bundle.extra.update({"source_scan": str(file), "scan_to_sim": res.sim3.to_dict()})
    save_scene(out, setup.bundle, setup.hierarchy, setup.info)
    rows = _report_views(out, setup.bundle.splats, views, None, with_lpips=False)
    report = {"scan": str(file), "bag": str(bag), "out": str(out), "splats": len(res.splats),
              "target": "fused masked depth", "target_points": int(len(target)), "sim3": res.sim3.to_dict(),
              "scale": res.sim3.s, "residual": res.info["residual"], "photometric": res.info.get("photometric"),
              "views": rows, "seconds": round(time.time() - t0, 1)}
    (out / "align.json").write_text(json.dumps(report, indent=2))
    return report
