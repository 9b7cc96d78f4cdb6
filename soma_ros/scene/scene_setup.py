"""Scene set-up from an episode: G_0, table plane, gravity, hierarchy, scene bundle;
and the per-episode initial state (G_0 moved onto an episode's first frame).

Steps of :func:`setup_scene` (paper Sec. 3 "Scene Initialization via R2S Mapping"):

1. **Object points**: masked depth (object AND NOT robot) of ``scene.frames`` from
   every camera, back-projected into the sim (= world) frame
   (:meth:`EpisodeData.object_points`).
2. **Splats**: voxel-grid averaging of points and colours, the voxel size found by
   bisection so that about ``scene.num_splats`` voxels are occupied (fewer if the
   depth has fewer points); isotropic splats of ``splat_scale_factor`` x their
   median nearest-neighbour spacing.
3. **Photometric refinement** with our renderer on those frames (colours,
   opacities, scales, orientations; L1 + D-SSIM on object pixels, alpha and depth
   terms, robot pixels ignored; positions and count fixed; no early stop: at the
   bags' resolution the held-back pixel blocks cut whole stretches of a thin object
   out of the loss and measure extrapolation, not the fit) -- :func:`soma_ros.scene.splat_fit.fit_splats`.
4. **Table plane** by RANSAC (:func:`fit_table_plane`) on non-object, non-robot
   depth within ``table_radius`` of the object; **gravity** = g times the plane
   normal oriented by the paper's sign rule with a fixed camera's view direction
   (:func:`gravity_from_camera`); the plane normal stored points against gravity.
5. **Hierarchy** (complete linkage at the object's thresholds) and the bundle.

Per-episode initial state (:func:`align_splats`): the model is per object, bound
to one G_0 (one hierarchy). An episode whose object lies elsewhere, or bent
differently (a rope never lies twice the same), starts from G_0 moved onto that
episode's frame-0 object points: a rigid ICP (several yaw hypotheses about the
table normal, trimmed point-to-point, Umeyama), then an as-rigid-as-possible
refinement in which every fine cluster of the hierarchy gets a rotation and a
translation, fitted to a symmetric truncated Chamfer distance with a rigidity
term between neighbouring clusters. Splat count, hierarchy membership and
colours are those of G_0.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Optional

import numpy as np
import torch

from soma_ros.core.calibration import fit_table_plane, gravity_from_camera
from soma_ros.core.geometry import quat_multiply, quat_normalize, rotmat_to_quat
from soma_ros.core.hierarchy import Hierarchy, build_hierarchy, complete_linkage_clusters
from soma_ros.core.scene_bundle import CameraSpec, SceneBundle
from soma_ros.core.splats import Splats

from soma_ros.scene.capture import CaptureViews, FitConfig, fit_splats
from soma_ros.scene.config import SceneConfig
from soma_ros.data.dataset import EpisodeData

__all__ = [
    "SceneSetup",
    "voxel_downsample",
    "splats_from_points",
    "fit_table_and_gravity",
    "setup_scene",
    "episode_views",
    "align_splats",
    "rigid_icp",
]


@dataclass
class SceneSetup:
    """Result of :func:`setup_scene`."""

    bundle: SceneBundle
    hierarchy: Hierarchy
    info: dict = field(default_factory=dict)


# ------------------------------------------------------------------ points -> splats
def voxel_downsample(points: torch.Tensor, colors: torch.Tensor, voxel: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Average points [N, 3] and colours [N, 3] per occupied voxel -> ([M, 3], [M, 3])."""
    key = torch.floor(points.double() / voxel).long()
    _, inv = torch.unique(key, dim=0, return_inverse=True)
    m = int(inv.max()) + 1
    cnt = torch.zeros(m, dtype=torch.float64).index_add_(0, inv, torch.ones(len(points), dtype=torch.float64))
    p = torch.zeros(m, 3, dtype=torch.float64).index_add_(0, inv, points.double()) / cnt[:, None]
    c = torch.zeros(m, 3, dtype=torch.float64).index_add_(0, inv, colors.double()) / cnt[:, None]
    return p.float(), c.float()


def splats_from_points(points: torch.Tensor, colors: torch.Tensor, target: int, total_mass: float,
                       scale_factor: float = 0.6, opacity: float = 0.9) -> tuple[Splats, float]:
    """Isotropic splats on a voxel grid with about ``target`` occupied voxels; returns (splats, the
    median nearest-neighbour spacing of their centres, m). Splat scale = ``scale_factor`` x spacing.

    The voxel size is bisected in log space between 0.2 mm and the cloud's extent.
    """
    if points.ndim != 2 or points.shape[1] != 3 or len(points) < 4:
        raise ValueError(f"scene set-up: need at least 4 object points, got {list(points.shape)} "
                         "(is the object visible with valid depth in the first frame?)")
    ext = float((points.max(0).values - points.min(0).values).max())
    lo, hi = math.log(2e-4), math.log(max(ext, 1e-3))
    best = None
    for _ in range(30):
        mid = 0.5 * (lo + hi)
        n = len(voxel_downsample(points, colors, math.exp(mid))[0])
        if best is None or abs(n - target) < abs(best[1] - target):
            best = (math.exp(mid), n)
        if n > target:
            lo = mid
        else:
            hi = mid
        if abs(n - target) <= max(1, target // 100):
            break
    voxel = best[0]
    p, c = voxel_downsample(points, colors, voxel)
    # splat size from the actual spacing (the voxel can be far below it when the depth is sparse)
    from scipy.spatial import cKDTree

    nn = cKDTree(p.double().numpy()).query(p.double().numpy(), k=2)[0][:, 1]
    spacing = float(np.median(nn))
    return Splats.from_points(p, c.clamp(0, 1), scale=scale_factor * spacing, opacity=opacity,
                              total_mass=total_mass), spacing


# ------------------------------------------------------------------ table and gravity
def fit_table_and_gravity(ep: EpisodeData, center: torch.Tensor, cfg: SceneConfig, t: int = 0) -> dict:
    """Table plane and gravity in the sim frame from frame t's non-object, non-robot depth.

    Returns {"normal" [3] (against gravity), "offset" d (n.x + d = 0), "gravity" [3] m/s^2,
    "inliers", "points", "sign_votes"}. The sign of gravity follows the paper's rule with the
    view direction of every fixed camera (a camera mounted on the robot is not used: its view
    can be nearly parallel to the table); they must agree.
    """
    pts = ep.background_points(t)
    near = (pts - center.float()).norm(dim=-1) < cfg.table_radius
    pts = pts[near]
    if len(pts) < 50:
        raise ValueError(f"episode {ep.name}: only {len(pts)} table points within {cfg.table_radius} m of the object; "
                         "cannot fit the table plane (raise scene.table_radius?)")
    n, d, inl = fit_table_plane(pts.double().numpy(), iters=cfg.table_iters, threshold=cfg.table_threshold,
                                return_inliers=True)
    fixed = [i for i, c in enumerate(ep.camera_names) if ep.mounts.get(c, (ep.world_frame,))[0] == ep.world_frame]
    views = fixed or list(range(ep.num_cameras))
    votes = []
    for i in views:
        try:
            votes.append(gravity_from_camera(n, ep.cam_to_world[t, i].numpy()))
        except ValueError:
            continue
    if not votes:
        raise ValueError(f"episode {ep.name}: every camera views the table edge-on; the gravity sign is undetermined")
    signs = [float(np.sign(v @ n)) for v in votes]
    if len(set(signs)) > 1:
        raise ValueError(f"episode {ep.name}: cameras disagree on the gravity sign ({signs}); check the camera poses")
    g_dir = votes[0]
    normal = -g_dir  # points to the object's side, against gravity
    offset = -float(normal @ (np.asarray(pts.double().numpy())[inl]).mean(0))
    # the object must lie on the positive side of the table
    side = float(normal @ center.double().numpy() + offset)
    if side < -0.01:
        raise ValueError(f"episode {ep.name}: the object centre is {-side:.3f} m below the fitted table plane; "
                         "the plane or the gravity sign is wrong")
    return {"normal": normal, "offset": offset, "gravity": cfg.g * g_dir, "inliers": int(inl.sum()),
            "points": int(len(pts)), "object_height": side}


# ------------------------------------------------------------------ photometric views
def episode_views(ep: EpisodeData, frames) -> CaptureViews:
    """Frames of an episode as capture views (V = frames x cameras), with their measured
    depth; robot pixels ignored."""
    imgs, masks, ign, depth, K, c2w, names = [], [], [], [], [], [], []
    for t in frames:
        for c in range(ep.num_cameras):
            imgs.append(ep.rgb[t, c])
            masks.append(ep.loss_mask[t, c])
            ign.append(ep.robot_mask[t, c])
            depth.append(ep.depth[t, c])
            K.append(ep.K[c])
            c2w.append(ep.cam_to_world[t, c])
            names.append(f"{ep.camera_names[c]}@{t}")
    from soma_ros.core.cameras import Cameras

    cams = Cameras.from_cam_to_world(torch.stack(K), torch.stack(c2w), ep.width, ep.height, names)
    return CaptureViews(torch.stack(imgs), torch.stack(masks), cams, ignore=torch.stack(ign),
                        depth=torch.stack(depth))


# ------------------------------------------------------------------ the whole set-up
def setup_scene(ep: EpisodeData, cfg: SceneConfig, object_name: str, robot_config: str, total_mass: float,
                thresholds, seed_fraction: float = 0.25, init_splats: Optional[Splats] = None,
                progress: bool = False) -> SceneSetup:
    """G_0 (or ``init_splats``, e.g. a user .ply already in the sim frame), table, gravity,
    hierarchy and a :class:`SceneBundle` from episode ``ep`` (see module docstring)."""
    info: dict = {"episode": ep.name, "frames": list(cfg.frames)}
    frames = [f for f in cfg.frames if f < ep.num_frames]
    if not frames:
        raise ValueError(f"scene.frames {cfg.frames} are all beyond the episode's {ep.num_frames} frames")
    pts, cols = ep.object_points(frames, erode_px=cfg.erode_px)
    info["fused_points"] = int(len(pts))
    if init_splats is None:
        g0, voxel = splats_from_points(pts, cols, cfg.num_splats, total_mass, cfg.splat_scale_factor, cfg.opacity)
        info["spacing_m"] = voxel
        if len(g0) < cfg.num_splats * 0.9:
            info["note"] = (f"the fused depth has only {len(pts)} points: {len(g0)} splats instead of "
                            f"{cfg.num_splats}")
        if cfg.photometric_iters > 0:
            views = episode_views(ep, frames)
            # the training cameras are these very cameras: colours are fitted to them too
            # the fit of `soma reconstruct --capture` with the set-up's constraints: the fused depth
            # positions and the splat count stay (no densification or pruning: the model's hierarchy
            # is built on this G_0), SH degree 0, every frame x camera view in each iteration
            fc = FitConfig(iters=cfg.photometric_iters, lr_means=0.0, lr_scales=cfg.photometric_lr_scale,
                           lr_quats=1e-3, lr_opacity=cfg.photometric_lr_opacity, lr_color=cfg.photometric_lr_color,
                           aniso_reg=cfg.photometric_aniso_reg, max_aniso=cfg.photometric_max_aniso,
                           sh_degree=0, densify_until=0, min_opacity=0.0, max_scale=1e9, views_per_iter=0,
                           check_fraction=0.0, log_every=max(1, cfg.photometric_iters // 5))
            fitted = fit_splats(g0, views, fc, progress=progress)
            # keep the fused positions and the mass; scales bounded by 3 x the spacing
            g0 = Splats(means=g0.means, quats=fitted.quats, scales=fitted.scales.clamp(max=3 * voxel),
                        opacities=fitted.opacities, sh_dc=fitted.sh_dc, mass=g0.mass)
            info["photometric_history"] = fc.history
    else:
        g0 = init_splats
        total = float(g0.mass.sum())
        if not total > 0:
            g0 = Splats(g0.means, g0.quats, g0.scales, g0.opacities, g0.sh_dc, g0.sh_rest,
                        g0.means.new_full((len(g0),), total_mass / len(g0)), g0.attrs)
    info["num_splats"] = len(g0)
    center = g0.means.mean(0)
    table = fit_table_and_gravity(ep, center, cfg, frames[0])
    info["table"] = {k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in table.items()}
    hier = build_hierarchy(g0.means.detach().float(), g0.mass.detach().float(), thresholds, seed_fraction)
    info["hierarchy_sizes"] = hier.sizes
    cams = []
    for i, name in enumerate(ep.camera_names):
        frame, T_top_cam = ep.mounts.get(name, (ep.world_frame, None))
        if frame == ep.world_frame:
            cams.append(CameraSpec(name, ep.width, ep.height, ep.K[i].numpy(), cam_to_sim=ep.cam_to_world[0, i].numpy()))
        else:
            cams.append(CameraSpec(name, ep.width, ep.height, ep.K[i].numpy(), mount_link=frame, link_to_cam=T_top_cam))
    bundle = SceneBundle(
        splats=g0, gravity=np.asarray(table["gravity"]), table_normal=np.asarray(table["normal"]),
        table_offset=float(table["offset"]), dt=float(ep.dt), sim_frame=ep.world_frame, object_name=object_name,
        robot_config=robot_config, base_to_sim=ep.base_to_sim.to_dict(), cameras=cams,
        extra={"source_episode": ep.name, "source_bag": str(ep.path), "hierarchy_sizes": hier.sizes,
               "fused_points": int(len(pts))},
    )
    return SceneSetup(bundle=bundle, hierarchy=hier, info=info)


# ------------------------------------------------------------------ per-episode alignment
def _rot_about(axis: np.ndarray, angle: float) -> np.ndarray:
    a = axis / np.linalg.norm(axis)
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + math.sin(angle) * K + (1 - math.cos(angle)) * K @ K


def rigid_icp(src: np.ndarray, dst: np.ndarray, up: np.ndarray, iters: int = 30, max_distance: float = 0.05,
              yaw_hypotheses: int = 12) -> tuple[np.ndarray, np.ndarray, float]:
    """Rigid (R, t) with dst ~ R src + t by trimmed point-to-point ICP from ``yaw_hypotheses``
    rotations about ``up`` (after centring); returns (R [3,3], t [3], symmetric RMS distance)."""
    from scipy.spatial import cKDTree

    from soma_ros.core.calibration import umeyama

    tree_d = cKDTree(dst)
    cs, cd = src.mean(0), dst.mean(0)
    best = None
    for k in range(max(1, yaw_hypotheses)):
        R = _rot_about(up, 2 * math.pi * k / max(1, yaw_hypotheses))
        t = cd - R @ cs
        for _ in range(iters):
            moved = src @ R.T + t
            dist, j = tree_d.query(moved)
            thr = max(max_distance, float(np.percentile(dist, 50)))  # never trim below the median
            keep = dist <= thr
            if keep.sum() < 3:
                break
            try:
                sim = umeyama(src[keep], dst[j[keep]], with_scale=False)
            except ValueError:
                break
            R_new, t_new = sim.R, sim.t
            done = np.abs(R_new - R).max() < 1e-7 and np.abs(t_new - t).max() < 1e-7
            R, t = R_new, t_new
            if done:
                break
        moved = src @ R.T + t
        d1, _ = tree_d.query(moved)
        d2, _ = cKDTree(moved).query(dst)
        err = math.sqrt(0.5 * (np.mean(np.minimum(d1, max_distance) ** 2) + np.mean(np.minimum(d2, max_distance) ** 2)))
        if best is None or err < best[2]:
            best = (R, t, err)
    return best


def _axis_angle_to_rotmat(w: torch.Tensor) -> torch.Tensor:
    """Rotation vectors [K, 3] -> rotation matrices [K, 3, 3] (Rodrigues, safe at 0)."""
    theta2 = (w * w).sum(-1, keepdim=True)
    theta = torch.sqrt(theta2 + 1e-24)
    a = torch.where(theta2 > 1e-12, torch.sin(theta) / theta, 1 - theta2 / 6)
    b = torch.where(theta2 > 1e-12, (1 - torch.cos(theta)) / theta2.clamp_min(1e-24), 0.5 - theta2 / 24)
    Kx = torch.zeros(w.shape[0], 3, 3, dtype=w.dtype)
    Kx[:, 0, 1], Kx[:, 0, 2] = -w[:, 2], w[:, 1]
    Kx[:, 1, 0], Kx[:, 1, 2] = w[:, 2], -w[:, 0]
    Kx[:, 2, 0], Kx[:, 2, 1] = -w[:, 1], w[:, 0]
    eye = torch.eye(3, dtype=w.dtype).expand_as(Kx)
    return eye + a[..., None] * Kx + b[..., None] * (Kx @ Kx)


def align_splats(g0: Splats, target: torch.Tensor, up, cfg: SceneConfig,
                 clusters: Optional[torch.Tensor] = None, thresholds=(0.02,)) -> tuple[Splats, dict]:
    """G_0 moved onto target points [M, 3] (an episode's fused frame-0 object points).

    ``up``: the table normal [3] (yaw hypotheses of the rigid stage turn about it).
    ``clusters``: fine-cluster index per splat [N] (the hierarchy's ``parents[0]``; built
    at ``thresholds[0]`` if None). Returns (splats: same count, colours, opacities,
    masses and attributes as G_0; moved means and rotated orientations, info dict with the
    RMS distances after each stage).
    """
    if len(target) < 4:
        raise ValueError(f"align_splats: only {len(target)} target points (object not visible in the first frame?)")
    src = g0.means.detach().double().numpy()
    dst = target.detach().double().numpy()
    up = np.asarray(up, dtype=np.float64)
    R, t, err_rigid = rigid_icp(src, dst, up, cfg.align_icp_iters, cfg.align_max_distance)
    info = {"rms_rigid": err_rigid}
    means = torch.from_numpy(src @ R.T + t)
    Rt = torch.from_numpy(R)
    quats = quat_normalize(quat_multiply(rotmat_to_quat(Rt)[None].expand(len(g0), 4), g0.quats.double()))
    if cfg.align_nonrigid_iters > 0:
        if clusters is None:
            clusters = torch.from_numpy(complete_linkage_clusters(means.numpy(), float(thresholds[0])))
        means, rots, err = _arap_refine(means, torch.from_numpy(dst), clusters.long(), cfg, float(thresholds[0]))
        quats = quat_normalize(quat_multiply(rotmat_to_quat(rots)[clusters.long()], quats))
        info["rms_nonrigid"] = err
    out = Splats(means=means.to(g0.means.dtype), quats=quats.to(g0.quats.dtype), scales=g0.scales.detach().clone(),
                 opacities=g0.opacities.detach().clone(), sh_dc=g0.sh_dc.detach().clone(),
                 sh_rest=g0.sh_rest.detach().clone(), mass=g0.mass.detach().clone(), attrs=g0.attrs.detach().clone())
    return out, info


@torch.enable_grad()
def _arap_refine(x: torch.Tensor, y: torch.Tensor, clusters: torch.Tensor, cfg: SceneConfig,
                 radius: float) -> tuple[torch.Tensor, torch.Tensor, float]:
    """Per-cluster rigid motions (rotation vector, translation) fitting x [N,3] to y [M,3]
    (truncated symmetric Chamfer + rigidity between neighbouring clusters)."""
    K = int(clusters.max()) + 1
    cnt = torch.bincount(clusters, minlength=K).double()
    c = torch.zeros(K, 3, dtype=torch.float64).index_add_(0, clusters, x) / cnt[:, None]
    # cluster graph: pairs of cluster centres within 2.5 x the cluster diameter
    from scipy.spatial import cKDTree

    pairs = cKDTree(c.numpy()).query_pairs(2.5 * radius, output_type="ndarray")
    if len(pairs) == 0:
        pairs = np.zeros((0, 2), dtype=np.int64)
    e = torch.from_numpy(pairs.astype(np.int64))
    w = torch.zeros(K, 3, dtype=torch.float64, requires_grad=True)
    t = torch.zeros(K, 3, dtype=torch.float64, requires_grad=True)
    opt = torch.optim.Adam([w, t], lr=cfg.align_nonrigid_lr)
    trunc = cfg.align_max_distance
    rel = x - c[clusters]
    scale = max(radius, 1e-3)
    err = float("nan")
    for it in range(cfg.align_nonrigid_iters + 1):
        R = _axis_angle_to_rotmat(w)
        xm = (R[clusters] @ rel[:, :, None])[:, :, 0] + c[clusters] + t[clusters]
        d = torch.cdist(xm, y)  # [N, M]
        d1 = d.min(1).values.clamp(max=trunc)
        d2 = d.min(0).values.clamp(max=trunc)
        fit = 0.5 * ((d1 ** 2).mean() + (d2 ** 2).mean())
        if it == cfg.align_nonrigid_iters:
            err = math.sqrt(float(fit.detach()))
            break
        if len(e):
            i, j = e[:, 0], e[:, 1]
            pred_j = (R[i] @ (c[j] - c[i])[:, :, None])[:, :, 0] + c[i] + t[i]
            pred_i = (R[j] @ (c[i] - c[j])[:, :, None])[:, :, 0] + c[j] + t[j]
            reg = (((pred_j - c[j] - t[j]) ** 2).sum(-1) + ((pred_i - c[i] - t[i]) ** 2).sum(-1)).mean()
        else:
            reg = x.new_zeros(())
        loss = fit / scale ** 2 + cfg.align_rigidity * reg / scale ** 2
        opt.zero_grad()
        loss.backward()
        opt.step()
    with torch.no_grad():
        R = _axis_angle_to_rotmat(w)
        xm = (R[clusters] @ rel[:, :, None])[:, :, 0] + c[clusters] + t[clusters]
    return xm.detach(), R.detach(), err
