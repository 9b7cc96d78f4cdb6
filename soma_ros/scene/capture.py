"""Multi-view capture folders: reading, visual hull, initial splats.

A capture folder (like ``shared/data/real_rope_4view``) holds, for V views:
``img_<i>.png`` (RGB), ``mask_<i>.png`` (object mask, >0 = object),
``intr_list.npy`` [V,3,3] pinhole intrinsics, ``R_list.npy`` [V,3,3] and
``t_list.npy`` [V,3] camera-to-world rotations and translations (OpenCV
optical axes), and optionally ``pcd.ply`` (object points, same world frame) and
``depth_<i>.png`` (16-bit, millimetres, camera z; 0 = no depth) or ``depth_<i>.npy``
(float metres).

The photometric fit lives in :mod:`soma_ros.scene.splat_fit` (re-exported here).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Optional, Sequence

import numpy as np
import torch

from soma_ros.core.cameras import Cameras
from soma_ros.core.splats import Splats

from soma_ros.scene.splat_fit import FitConfig, fit_splats  # noqa: F401  (the fit of capture views)


@dataclass
class CaptureViews:
    """V calibrated views of one static scene."""

    images: torch.Tensor  # [V, H, W, 3] float32 in [0, 1]
    masks: torch.Tensor  # [V, H, W] bool, object pixels
    cameras: Cameras  # V cameras
    points: Optional[torch.Tensor] = None  # [N, 3] object points, if the capture has them
    point_colors: Optional[torch.Tensor] = None  # [N, 3] in [0, 1]
    ignore: Optional[torch.Tensor] = None  # [V, H, W] bool: pixels no loss looks at (e.g. robot-occluded)
    depth: Optional[torch.Tensor] = None  # [V, H, W] float metres (camera z), 0 = no depth

    def __post_init__(self) -> None:
        V, H, W = self.images.shape[:3]
        if self.images.shape != (V, H, W, 3) or tuple(self.masks.shape) != (V, H, W):
            raise ValueError(f"CaptureViews: images must be [V, H, W, 3] and masks [V, H, W], got "
                             f"{list(self.images.shape)} and {list(self.masks.shape)}")
        if len(self.cameras) != V or (self.cameras.width, self.cameras.height) != (W, H):
            raise ValueError(f"CaptureViews: {len(self.cameras)} cameras of {self.cameras.width}x{self.cameras.height} "
                             f"for {V} views of {W}x{H}")
        if self.ignore is not None and tuple(self.ignore.shape) != (V, H, W):
            raise ValueError(f"CaptureViews: ignore must be [V, H, W], got {list(self.ignore.shape)}")
        if self.depth is not None and tuple(self.depth.shape) != (V, H, W):
            raise ValueError(f"CaptureViews: depth must be [V, H, W], got {list(self.depth.shape)}")

    @property
    def num_views(self) -> int:
        return int(self.images.shape[0])

    def select(self, idx: Sequence[int]) -> "CaptureViews":
        i = torch.as_tensor(list(idx), dtype=torch.long)
        return CaptureViews(self.images[i], self.masks[i], self.cameras.select(list(idx)), self.points, self.point_colors,
                            None if self.ignore is None else self.ignore[i], None if self.depth is None else self.depth[i])

    def resized(self, factor: float) -> "CaptureViews":
        """Views at `factor` x the resolution (area-averaged images, nearest masks)."""
        if factor == 1.0:
            return self
        import cv2

        H, W = self.images.shape[1:3]
        w, h = int(round(W * factor)), int(round(H * factor))
        imgs = np.stack([cv2.resize(im, (w, h), interpolation=cv2.INTER_AREA) for im in self.images.numpy()])
        msk = np.stack([cv2.resize(m.astype(np.uint8), (w, h), interpolation=cv2.INTER_NEAREST) for m in self.masks.numpy()])
        ign = None
        if self.ignore is not None:
            ign = torch.from_numpy(np.stack([cv2.resize(m.astype(np.uint8), (w, h), interpolation=cv2.INTER_NEAREST)
                                             for m in self.ignore.numpy()]) > 0)
        dep = None
        if self.depth is not None:
            dep = torch.from_numpy(np.stack([cv2.resize(d, (w, h), interpolation=cv2.INTER_NEAREST)
                                             for d in self.depth.numpy()]))
        return CaptureViews(torch.from_numpy(imgs), torch.from_numpy(msk > 0), self.cameras.scaled(factor),
                            self.points, self.point_colors, ign, dep)

    def with_point_depth(self) -> "CaptureViews":
        """These views with sparse depth where they have none: the capture's object points
        projected into every view (nearest point per pixel, only on object pixels)."""
        if self.points is None or len(self.points) == 0:
            return self
        V, H, W = self.masks.shape
        uv, z = self.cameras.project(self.points.to(self.cameras.K.dtype))
        depth = torch.zeros(V, H, W) if self.depth is None else self.depth.clone()
        for v in range(V):
            u_i, v_i = uv[v, :, 0].floor().long(), uv[v, :, 1].floor().long()
            ok = (z[v] > 0.01) & (u_i >= 0) & (u_i < W) & (v_i >= 0) & (v_i < H)
            lin = v_i[ok] * W + u_i[ok]
            zz = z[v][ok].float()
            best = torch.full((H * W,), float("inf")).scatter_reduce(0, lin, zz, reduce="amin")
            best = best.reshape(H, W)
            fill = torch.isfinite(best) & self.masks[v] & (depth[v] <= 0)
            depth[v][fill] = best[fill]
        return CaptureViews(self.images, self.masks, self.cameras, self.points, self.point_colors, self.ignore, depth)


def read_capture(folder: str | Path) -> CaptureViews:
    import cv2

    folder = Path(folder)
    if not folder.is_dir():
        raise FileNotFoundError(f"capture folder not found: {folder}")
    need = ["intr_list.npy", "R_list.npy", "t_list.npy"]
    missing = [n for n in need if not (folder / n).is_file()]
    if missing:
        raise FileNotFoundError(f"capture folder {folder} lacks {', '.join(missing)}")
    K = np.load(folder / "intr_list.npy").astype(np.float64)
    R = np.load(folder / "R_list.npy").astype(np.float64)
    t = np.load(folder / "t_list.npy").astype(np.float64)
    V = K.shape[0]
    if K.shape != (V, 3, 3) or R.shape != (V, 3, 3) or t.shape != (V, 3):
        raise ValueError(f"capture arrays disagree: intr {K.shape}, R {R.shape}, t {t.shape}")
    imgs, masks, depths = [], [], []
    for i in range(V):
        ip, mp = folder / f"img_{i}.png", folder / f"mask_{i}.png"
        if not ip.is_file() or not mp.is_file():
            raise FileNotFoundError(f"capture folder {folder} lacks {ip.name} or {mp.name}")
        im = cv2.imread(str(ip), cv2.IMREAD_COLOR)[..., ::-1]
        m = cv2.imread(str(mp), cv2.IMREAD_UNCHANGED)
        if m.ndim == 3:
            m = m[..., 0]
        if m.shape != im.shape[:2]:
            raise ValueError(f"{mp.name} is {m.shape[1]}x{m.shape[0]}, image is {im.shape[1]}x{im.shape[0]}")
        imgs.append(im.astype(np.float32) / 255.0)
        masks.append(m > 0)
        dp, dn = folder / f"depth_{i}.png", folder / f"depth_{i}.npy"
        if dp.is_file() or dn.is_file():
            d = (cv2.imread(str(dp), cv2.IMREAD_UNCHANGED).astype(np.float32) / 1000.0 if dp.is_file()
                 else np.load(dn).astype(np.float32))
            if d.shape != im.shape[:2]:
                raise ValueError(f"{(dp if dp.is_file() else dn).name} is {d.shape[1]}x{d.shape[0]}, image is "
                                 f"{im.shape[1]}x{im.shape[0]}")
            depths.append(np.where(np.isfinite(d), d, 0.0))
        elif depths:
            raise FileNotFoundError(f"capture folder {folder} has depth for some views but not for view {i}")
    H, W = imgs[0].shape[:2]
    c2w = np.tile(np.eye(4), (V, 1, 1))
    c2w[:, :3, :3] = R
    c2w[:, :3, 3] = t
    cams = Cameras.from_cam_to_world(K, c2w, W, H, names=[f"view_{i}" for i in range(V)])
    pts = cols = None
    if (folder / "pcd.ply").is_file():
        from soma_ros.core.ply import read_ply

        pc = read_ply(folder / "pcd.ply")  # a plain x/y/z/red/green/blue cloud reads as isotropic splats
        pts, cols = pc.means.float(), pc.colors().float()
    dep = torch.from_numpy(np.stack(depths)) if depths else None
    return CaptureViews(torch.from_numpy(np.stack(imgs)), torch.from_numpy(np.stack(masks)), cams, pts, cols, None, dep)


def visual_hull(views: CaptureViews, bounds_min: torch.Tensor, bounds_max: torch.Tensor, voxel: float,
                min_views: Optional[int] = None) -> torch.Tensor:
    """Centres [N, 3] of voxels whose projection is inside the object mask of every
    view that sees them (and at least `min_views` views)."""
    axes = [torch.arange(float(bounds_min[i]), float(bounds_max[i]), voxel) for i in range(3)]
    grid = torch.stack(torch.meshgrid(*axes, indexing="ij"), dim=-1).reshape(-1, 3)
    inside = torch.ones(grid.shape[0], dtype=torch.bool)
    seen = torch.zeros(grid.shape[0], dtype=torch.long)
    uv, z = views.cameras.project(grid.to(views.cameras.K.dtype))
    H, W = views.masks.shape[1:3]
    for v in range(views.num_views):
        u_i = uv[v, :, 0].round().long()
        v_i = uv[v, :, 1].round().long()
        ok = (z[v] > 0.01) & (u_i >= 0) & (u_i < W) & (v_i >= 0) & (v_i < H)
        hit = torch.zeros_like(ok)
        hit[ok] = views.masks[v][v_i[ok], u_i[ok]]
        inside &= hit | ~ok
        seen += ok.long()
    need = views.num_views if min_views is None else min_views
    return grid[inside & (seen >= need)]


def initial_splats_from_capture(views: CaptureViews, train_idx: Sequence[int], voxel: float = 0.004,
                                init_scale: Optional[float] = None) -> Splats:
    """Initial splats: the capture's object points when it has them, else the visual hull
    of the training views' masks; colours sampled from the training images. Scale:
    ``init_scale`` metres, or (None) the mean distance to the 3 nearest neighbours (3DGS)."""
    if views.points is not None and len(views.points) > 0:
        pts = views.points.float()
    else:
        tv = views.select(train_idx)
        centres = tv.cameras.centers().float()
        lo, hi = centres.min(0).values - 1.0, centres.max(0).values + 1.0
        pts = visual_hull(tv, lo, hi, voxel * 4)
        if len(pts) == 0:
            raise ValueError("visual hull is empty: masks and camera poses disagree")
        span_lo, span_hi = pts.min(0).values - 4 * voxel, pts.max(0).values + 4 * voxel
        pts = visual_hull(tv, span_lo, span_hi, voxel).float()
    # colour: mean of the training views that see the point inside the mask
    tv = views.select(train_idx)
    uv, z = tv.cameras.project(pts.to(tv.cameras.K.dtype))
    H, W = tv.images.shape[1:3]
    acc = torch.zeros(len(pts), 3)
    cnt = torch.zeros(len(pts), 1)
    for v in range(tv.num_views):
        u_i, v_i = uv[v, :, 0].round().long(), uv[v, :, 1].round().long()
        ok = (z[v] > 0) & (u_i >= 0) & (u_i < W) & (v_i >= 0) & (v_i < H)
        ok[ok.clone()] &= tv.masks[v][v_i[ok], u_i[ok]]
        acc[ok] += tv.images[v][v_i[ok], u_i[ok]]
        cnt[ok] += 1
    colors = torch.where(cnt > 0, acc / cnt.clamp_min(1), torch.full_like(acc, 0.5))
    if views.point_colors is not None and views.points is not None and len(views.point_colors) == len(pts):
        colors = torch.where(cnt > 0, colors, views.point_colors.float())
    if init_scale is None:
        from scipy.spatial import cKDTree

        x = pts.double().numpy()
        d = cKDTree(x).query(x, k=min(4, len(x)))[0][:, 1:]
        scales = torch.from_numpy(d.mean(1)).float().clamp_min(1e-5)[:, None].expand(-1, 3).contiguous()
        sp = Splats.from_points(pts, colors.clamp(0, 1), scale=1.0, opacity=0.5)
        return Splats(sp.means, sp.quats, scales, sp.opacities, sp.sh_dc, mass=sp.mass)
    return Splats.from_points(pts, colors.clamp(0, 1), scale=init_scale, opacity=0.8)
