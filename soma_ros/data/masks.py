"""Object and robot masks for bags that record none, from geometry only (no model weights).

A real rig's camera drivers publish colour and depth, not masks. The trainer
needs, per camera and frame, the object's pixels (supervised) and the robot's
pixels (excluded). :func:`derive_masks` makes both from the episode's depth,
camera poses and joint states:

1. **Robot.** The URDF's link meshes (``robot_geometry``: ``collision`` or
   ``visual``; gripper fingers are links too) are posed by FK from the joint
   states and rasterized into every camera with its own intrinsics
   (:mod:`soma_ros.core.robot_meshes`). A pixel is the robot's where the mesh
   renders and the measured depth sees nothing nearer than the rendered surface
   minus ``robot_depth_tolerance`` (so an object held in front of the arm stays
   the object's).
2. **Table.** A plane fitted by RANSAC to the non-robot depth of the first
   frame (all cameras fused, in the world frame), with its normal within
   ``max_tilt_deg`` of the world's +z (REP 103: z up), then refined by least
   squares on its inliers. The height threshold ``min_height`` defaults to
   four robust standard deviations of the inliers' residuals (at least 2 mm),
   so it follows the sensor's noise.
3. **Object.** Candidate pixels stand between ``min_height`` and ``max_height``
   above the plane, inside the workspace (``workspace``: a world box, by
   default the convex extent of the table's inliers, as seen from above), and
   are not the robot's. In the first frame the candidates' fused 3D points are
   split into connected components on a ``voxel`` grid; components of at least
   ``min_component_points`` points are the object (``components: largest``
   keeps one). In each later frame the candidate components that come within
   ``track_radius`` of the previous frame's object points are the object, so it
   is tracked when lifted off the table.

Limits: the object must stand out of the table by more than the depth noise,
and anything else on the table in the first frame counts as object unless
``components: largest`` or a ``workspace`` box excludes it. Masks the user
supplies win (:func:`load_mask_folder`; mask topics in the bag).

Shapes: masks are [T, H, W] bool per camera at the recorded resolution.
"""

from __future__ import annotations

import hashlib
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Mapping, Optional, Sequence

import numpy as np

from soma_ros.core.config import ConfigError

from soma_ros.data.bags import BagError, Episode

__all__ = ["MaskConfig", "TablePlane", "DerivedMasks", "derive_masks", "fit_table_plane", "load_mask_folder",
           "mask_iou"]

MASK_SOURCES = ("auto", "bag", "folder", "derive")


@dataclass
class MaskConfig:
    """Where the object / robot masks come from (``source``) and how they are derived.

    ``source``: ``auto`` (the bag's mask topics, else ``folder`` when set, else derived),
    ``bag`` (mask topics required), ``folder`` (PNGs required), ``derive`` (always derived).
    ``folder``: ``FOLDER/<episode>/<camera>/object_<frame:06d>.png`` (and optionally
    ``robot_<frame:06d>.png``), non-zero = inside; frame = index of the synchronised frame.
    See the module docstring for the derivation parameters (lengths in metres).
    """

    source: str = "auto"
    folder: Optional[str] = None
    robot_geometry: str = "collision"
    robot_depth_tolerance: float = 0.02
    robot_dilate_px: int = 0
    plane_frames: list[int] = field(default_factory=lambda: [0])
    plane_inlier: float = 0.01
    max_tilt_deg: float = 30.0
    min_height: Optional[float] = None
    max_height: float = 0.5
    workspace: Optional[list[float]] = None
    voxel: float = 0.01
    min_component_points: int = 20
    components: str = "all"
    track_radius: float = 0.03
    seed: int = 0

    def validate(self, where: str = "data.masks") -> None:
        if self.source not in MASK_SOURCES:
            raise ConfigError(f"{where}.source: must be one of {', '.join(MASK_SOURCES)}, got {self.source!r}")
        if self.source == "folder" and not self.folder:
            raise ConfigError(f"{where}.folder: must be set when source is 'folder'")
        if self.robot_geometry not in ("collision", "visual"):
            raise ConfigError(f"{where}.robot_geometry: must be 'collision' or 'visual', got {self.robot_geometry!r}")
        if self.components not in ("all", "largest"):
            raise ConfigError(f"{where}.components: must be 'all' or 'largest', got {self.components!r}")
        if self.workspace is not None and len(self.workspace) != 6:
            raise ConfigError(f"{where}.workspace: [xmin, xmax, ymin, ymax, zmin, zmax] in the world frame")
        for k in ("robot_depth_tolerance", "plane_inlier", "max_height", "voxel", "track_radius"):
            v = getattr(self, k)
            if not (v > 0 and math.isfinite(v)):
                raise ConfigError(f"{where}.{k}: must be > 0, got {v}")
        if self.min_height is not None and not self.min_height >= 0:
            raise ConfigError(f"{where}.min_height: must be >= 0 or null, got {self.min_height}")
        if self.robot_dilate_px < 0 or self.min_component_points < 1 or not self.plane_frames:
            raise ConfigError(f"{where}: robot_dilate_px >= 0, min_component_points >= 1, plane_frames non-empty")


@dataclass
class TablePlane:
    """n . p + d = 0 in the world frame (n [3] unit, pointing up); heights are n . p + d."""

    normal: np.ndarray
    offset: float
    sigma: float  # robust std of the inliers' residuals, m
    inliers: int
    hull_xy: Optional[np.ndarray] = None  # [K, 2] convex extent of the inliers in world x, y

    def height(self, P: np.ndarray) -> np.ndarray:
        return P @ self.normal + self.offset


@dataclass
class DerivedMasks:
    """Per camera [T, H, W] bool masks, with what the derivation found."""

    object_mask: dict[str, np.ndarray]
    robot_mask: dict[str, np.ndarray]
    planes: dict[str, TablePlane]  # per camera
    min_height: dict[str, float]  # per camera, m
    info: dict = field(default_factory=dict)


def _pixel_points(depth: np.ndarray, K: np.ndarray, c2w: np.ndarray) -> np.ndarray:
    """World points [H, W, 3] of a depth image [H, W] (OpenCV optical frame; pixel (col, row) has its
    centre at (col, row), the sensor_msgs/CameraInfo convention)."""
    H, W = depth.shape
    u = np.arange(W, dtype=np.float64)
    v = np.arange(H, dtype=np.float64)
    x = (u[None, :] - K[0, 2]) / K[0, 0] * depth
    y = (v[:, None] - K[1, 2]) / K[1, 1] * depth
    pc = np.stack([x, y, depth], axis=-1)
    return pc @ c2w[:3, :3].T + c2w[:3, 3]


def fit_table_plane(points: np.ndarray, inlier: float = 0.01, max_tilt_deg: float = 30.0, iters: int = 300,
                    seed: int = 0) -> Optional[TablePlane]:
    """RANSAC (MSAC scoring: residuals truncated at ``inlier``) plane through world points [N, 3] among
    planes whose normal is within ``max_tilt_deg`` of +z, refined by least squares; None when no such
    plane is found."""
    assert points.ndim == 2 and points.shape[1] == 3, points.shape
    if len(points) < 50:
        return None
    rng = np.random.default_rng(seed)
    P = points if len(points) <= 30000 else points[rng.choice(len(points), 30000, replace=False)]
    cos_tilt = math.cos(math.radians(max_tilt_deg))
    best, best_n, best_d = math.inf, None, 0.0  # MSAC: truncated squared residuals (the tightest plane wins)
    for _ in range(iters):
        a, b, c = P[rng.choice(len(P), 3, replace=False)]
        n = np.cross(b - a, c - a)
        nn = np.linalg.norm(n)
        if nn < 1e-9:
            continue
        n = n / nn
        if n[2] < 0:
            n = -n
        if n[2] < cos_tilt:
            continue
        d = -float(n @ a)
        k = float(np.minimum((P @ n + d) ** 2, inlier * inlier).sum())
        if k < best:
            best, best_n, best_d = k, n, d
    if best_n is None:
        return None
    n, d, thr = best_n, best_d, inlier
    for _ in range(3):
        r = points @ n + d
        sel = points[np.abs(r) < thr]
        if len(sel) < 3:
            break
        c = sel.mean(0)
        _, _, Vt = np.linalg.svd(sel - c, full_matrices=False)
        n = Vt[-1] if Vt[-1][2] >= 0 else -Vt[-1]
        d = -float(n @ c)
        r = sel @ n + d
        sigma = 1.4826 * float(np.median(np.abs(r - np.median(r))))
        thr = max(3.0 * sigma, 0.002)
    r = points @ n + d
    inl = points[np.abs(r) < thr]
    sigma = 1.4826 * float(np.median(np.abs(r[np.abs(r) < thr]))) if len(inl) else 0.0
    hull = None
    if len(inl) >= 3:
        from scipy.spatial import ConvexHull, QhullError

        try:
            h = ConvexHull(inl[:, :2])
            hull = inl[h.vertices, :2]
        except (QhullError, ValueError):
            hull = None
    return TablePlane(normal=n, offset=d, sigma=sigma, inliers=len(inl), hull_xy=hull)


def refine_plane(points: np.ndarray, start: TablePlane, window: float, max_turn_deg: float = 2.0) -> TablePlane:
    """One camera's own view of a shared table plane: ``start`` moved along its normal by the median
    residual of the points [N, 3] within ``window``, then re-fitted by least squares to the points
    within 3 robust sigmas (at least 2 mm, at most ``window``); the normal turns by at most
    ``max_turn_deg`` (else only the offset changes)."""
    n, d = start.normal, start.offset
    r = points @ n + d
    sel = np.abs(r) < window
    if sel.sum() < 10:
        return start
    d -= float(np.median(r[sel]))
    for _ in range(2):
        r = points @ n + d
        sigma = 1.4826 * float(np.median(np.abs(r[np.abs(r) < window])))
        thr = min(window, max(3.0 * sigma, 0.002))
        sel = points[np.abs(r) < thr]
        if len(sel) < 10:
            break
        c = sel.mean(0)
        _, _, Vt = np.linalg.svd(sel - c, full_matrices=False)
        m = Vt[-1] if Vt[-1][2] >= 0 else -Vt[-1]
        if float(m @ start.normal) >= math.cos(math.radians(max_turn_deg)):
            n = m
        d = -float(n @ c)
    r = points @ n + d
    sigma = 1.4826 * float(np.median(np.abs(r[np.abs(r) < window])))
    inl = np.abs(r) < min(window, max(3.0 * sigma, 0.002))
    hull = None
    if inl.sum() >= 3:
        from scipy.spatial import ConvexHull, QhullError

        try:
            hull = points[inl][ConvexHull(points[inl][:, :2]).vertices, :2]
        except (QhullError, ValueError):
            hull = None
    return TablePlane(normal=n, offset=d, sigma=sigma, inliers=int(inl.sum()), hull_xy=hull)


def _in_hull(xy: np.ndarray, hull: np.ndarray) -> np.ndarray:
    """[N] bool: points [N, 2] inside the convex polygon hull [K, 2] (counter-clockwise, as qhull gives)."""
    inside = np.ones(len(xy), bool)
    for i in range(len(hull)):
        a, b = hull[i], hull[(i + 1) % len(hull)]
        inside &= (b[0] - a[0]) * (xy[:, 1] - a[1]) - (b[1] - a[1]) * (xy[:, 0] - a[0]) >= -1e-9
    return inside


def _components(points: np.ndarray, voxel: float) -> tuple[np.ndarray, int]:
    """Connected components (26-neighbourhood on a voxel grid) of points [N, 3] -> (label [N] >= 0, count)."""
    from scipy import ndimage

    if len(points) == 0:
        return np.zeros(0, np.int64), 0
    ijk = np.floor((points - points.min(0)) / voxel).astype(np.int64)
    shape = ijk.max(0) + 1
    while int(np.prod(shape)) > 30_000_000:  # a huge spread: coarsen rather than run out of memory
        voxel *= 2.0
        ijk = np.floor((points - points.min(0)) / voxel).astype(np.int64)
        shape = ijk.max(0) + 1
    grid = np.zeros(tuple(shape), bool)
    grid[ijk[:, 0], ijk[:, 1], ijk[:, 2]] = True
    lab, n = ndimage.label(grid, structure=np.ones((3, 3, 3), bool))
    return lab[ijk[:, 0], ijk[:, 1], ijk[:, 2]] - 1, int(n)


def _dilate(mask: np.ndarray, px: int) -> np.ndarray:
    if px <= 0:
        return mask
    import cv2

    k = np.ones((2 * px + 1, 2 * px + 1), np.uint8)
    return cv2.dilate(mask.astype(np.uint8), k) > 0


def derive_masks(ep: Episode, link_to_world: Mapping[str, np.ndarray], meshes: Mapping, cfg: MaskConfig,
                 cameras: Optional[Sequence[str]] = None, progress: bool = False) -> DerivedMasks:
    """Robot and object masks of every camera of ``ep`` (poses resolved: ``cam_to_world`` set) from
    ``link_to_world`` {link: [T, 4, 4]} world poses of the robot links and their ``meshes``
    (:func:`soma_ros.core.robot_meshes.load_link_meshes`). See the module docstring."""
    from scipy.spatial import cKDTree

    from soma_ros.core.robot_meshes import render_depth, robot_pixels

    T = ep.num_frames
    names = list(cameras) if cameras is not None else sorted(ep.cameras)
    for c in names:
        s = ep.cameras[c]
        if s.cam_to_world is None or s.depth is None:
            raise BagError(f"{ep.path.name}: camera '{c}' needs depth and a pose to derive masks")
    it = range(T)
    if progress:
        from tqdm import tqdm

        it = tqdm(it, desc=f"masks {ep.path.name}", unit="frame", leave=False)
    robot = {c: np.zeros((T, ep.cameras[c].height, ep.cameras[c].width), bool) for c in names}
    points = {c: np.zeros((T, ep.cameras[c].height, ep.cameras[c].width, 3)) for c in names}
    for t in it:
        L = {k: v[t] for k, v in link_to_world.items()}
        for c in names:
            s = ep.cameras[c]
            d = render_depth(meshes, L, s.K, s.cam_to_world[t], s.width, s.height)
            robot[c][t] = _dilate(robot_pixels(d, s.depth[t], cfg.robot_depth_tolerance), cfg.robot_dilate_px)
            points[c][t] = _pixel_points(s.depth[t].astype(np.float64), s.K, s.cam_to_world[t])

    # ---- table plane per camera (a camera's own depth bias and calibration error cancel in its
    # heights) from the non-robot depth of the plane frames; the workspace from all cameras' inliers
    def plane_points(c: str) -> np.ndarray:
        fused = []
        for t in cfg.plane_frames:
            if not 0 <= t < T:
                raise BagError(f"{ep.path.name}: data.masks.plane_frames: frame {t} out of range [0, {T})")
            ok = (ep.cameras[c].depth[t] > 0) & ~robot[c][t]
            fused.append(points[c][t][ok])
        return np.concatenate(fused)

    per_cam = {c: plane_points(c) for c in names}
    rng = np.random.default_rng(cfg.seed)
    n_each = min(len(p) for p in per_cam.values())
    if n_each < 50:
        raise BagError(f"{ep.path.name}: too little valid depth in frame(s) {cfg.plane_frames} to find the table")
    # cameras weigh equally in the shared plane (a close-up camera has many more pixels on a small area)
    shared = np.concatenate([p[rng.choice(len(p), min(len(p), 5000), replace=False)] for p in per_cam.values()])
    base = fit_table_plane(shared, cfg.plane_inlier, cfg.max_tilt_deg, seed=cfg.seed)
    if base is None:
        raise BagError(f"{ep.path.name}: no table plane in the depth of frame(s) {cfg.plane_frames} "
                       f"(normal within {cfg.max_tilt_deg:.0f} deg of world +z); supply masks or data.masks.workspace")
    planes: dict[str, TablePlane] = {c: refine_plane(per_cam[c], base, 0.5 * cfg.plane_inlier) for c in names}
    hull = None
    corners = [pl.hull_xy for pl in planes.values() if pl.hull_xy is not None]
    if corners and cfg.workspace is None:
        from scipy.spatial import ConvexHull, QhullError

        allc = np.concatenate(corners)
        try:
            hull = allc[ConvexHull(allc).vertices]
        except (QhullError, ValueError):
            hull = None
    min_hs = {c: cfg.min_height if cfg.min_height is not None else max(0.002, 4.0 * pl.sigma)
              for c, pl in planes.items()}

    def candidates(t: int) -> dict[str, np.ndarray]:
        out = {}
        for c in names:
            P = points[c][t]
            h = planes[c].height(P.reshape(-1, 3)).reshape(P.shape[:2])
            m = (ep.cameras[c].depth[t] > 0) & ~robot[c][t] & (h > min_hs[c]) & (h < cfg.max_height)
            if cfg.workspace is not None:
                x0, x1, y0, y1, z0, z1 = cfg.workspace
                m &= (P[..., 0] >= x0) & (P[..., 0] <= x1) & (P[..., 1] >= y0) & (P[..., 1] <= y1)
                m &= (P[..., 2] >= z0) & (P[..., 2] <= z1)
            elif hull is not None:
                flat = m.reshape(-1)
                idx = np.nonzero(flat)[0]
                flat[idx[~_in_hull(P.reshape(-1, 3)[idx, :2], hull)]] = False
            out[c] = m
        return out

    obj = {c: np.zeros_like(robot[c]) for c in names}
    prev: Optional[np.ndarray] = None
    kept_first = 0
    for t in range(T):
        cand = candidates(t)
        pts = np.concatenate([points[c][t][cand[c]] for c in names])
        lab, n = _components(pts, cfg.voxel)
        if t == 0 or prev is None or len(prev) == 0:
            sizes = np.bincount(lab, minlength=n) if n else np.zeros(0, np.int64)
            keep = np.nonzero(sizes >= cfg.min_component_points)[0]
            if cfg.components == "largest" and len(keep):
                keep = keep[np.argmax(sizes[keep])][None]
            if t == 0:
                kept_first = len(keep)
        else:
            near = cKDTree(prev).query(pts, k=1, distance_upper_bound=cfg.track_radius)[0] < np.inf if len(pts) else np.zeros(0, bool)
            keep = np.unique(lab[near])
        sel = np.isin(lab, keep)
        prev = pts[sel]
        k = 0
        for c in names:
            m = cand[c]
            nm = int(m.sum())
            o = np.zeros_like(m)
            o[m] = sel[k: k + nm]
            k += nm
            obj[c][t] = o
    info = {"planes": {c: {"normal": [round(float(v), 5) for v in pl.normal], "offset": round(pl.offset, 5),
                           "sigma_m": round(pl.sigma, 5), "inliers": pl.inliers, "min_height_m": round(min_hs[c], 5)}
                       for c, pl in planes.items()},
            "components_frame0": kept_first, "robot_geometry": cfg.robot_geometry}
    return DerivedMasks(obj, robot, planes, min_hs, info)


def load_mask_folder(folder: Path, episode: str, camera: str, num_frames: int, height: int, width: int,
                     kind: str = "object") -> Optional[np.ndarray]:
    """[T, H, W] bool from ``folder/<episode>/<camera>/<kind>_<frame:06d>.png``; None when that camera's
    folder has no such file; a BagError naming the file for a missing frame or a wrong size."""
    import cv2

    d = Path(folder) / episode / camera
    files = [d / f"{kind}_{t:06d}.png" for t in range(num_frames)]
    if not d.is_dir() or not any(f.is_file() for f in files):
        return None
    out = np.zeros((num_frames, height, width), bool)
    for t, f in enumerate(files):
        if not f.is_file():
            raise BagError(f"{f}: missing (the mask folder has other {kind} frames of camera '{camera}')")
        img = cv2.imread(str(f), cv2.IMREAD_GRAYSCALE)
        if img is None or img.shape != (height, width):
            raise BagError(f"{f}: not a {width}x{height} image")
        out[t] = img > 0
    return out


def mask_iou(a: np.ndarray, b: np.ndarray) -> float:
    """Intersection over union of two bool masks (1.0 when both are empty)."""
    u = int((a | b).sum())
    return 1.0 if u == 0 else int((a & b).sum()) / u


def cache_key(bag: Path, cfg: MaskConfig, cameras: Sequence[str], frames: int, extra: str = "") -> str:
    """A key for a bag's derived masks: the bag's files (names, sizes, mtimes) and the settings."""
    bag = Path(bag)
    files = sorted(bag.rglob("*")) if bag.is_dir() else [bag]
    h = hashlib.sha1()
    for f in files:
        if f.is_file():
            st = f.stat()
            h.update(f"{f.name}:{st.st_size}:{int(st.st_mtime)};".encode())
    cfgd = {k: v for k, v in cfg.__dict__.items() if k not in ("source", "folder")}
    h.update(json.dumps([cfgd, list(cameras), frames, extra], sort_keys=True, default=str).encode())
    return h.hexdigest()[:16]
