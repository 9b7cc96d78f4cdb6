"""Pinhole cameras for the splat renderer.

A :class:`Cameras` holds C pinhole cameras that share one image size:

==============  ===========  ==============================================
field           shape        meaning
==============  ===========  ==============================================
K               [C, 3, 3]    intrinsics in pixels (fx, fy, cx, cy; no skew
                             is assumed by the renderer, K[:, 0, 1] ignored)
world_to_cam    [C, 4, 4]    rigid world -> camera transform
width, height   int          image size in pixels
names           list[str]    optional camera names (len C) or None
==============  ===========  ==============================================

Camera frame convention (OpenCV optical frame, also used by gsplat and by
RealSense ``*_optical_frame``): x right, y down, z forward. A camera-frame
point (x, y, z) with z > 0 projects to the pixel ``(fx x / z + cx,
fy y / z + cy)``, where pixel (col, row) has its centre at (col + 0.5,
row + 0.5) -- the gsplat / 3DGS convention. ``sensor_msgs/CameraInfo`` (and OpenCV,
RealSense) put that centre at (col, row), so its ``cx, cy`` are half a pixel smaller:
:func:`k_from_camera_info` and :func:`k_to_camera_info` convert at the ROS boundary.

Pure torch; no ROS imports.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional, Sequence, Union

import numpy as np
import torch

__all__ = ["Cameras", "look_at", "frame_points", "k_from_camera_info", "k_to_camera_info"]

_ArrayLike = Union[torch.Tensor, np.ndarray, Sequence]


def k_from_camera_info(k: _ArrayLike, scale_x: float = 1.0, scale_y: float = 1.0) -> np.ndarray:
    """``sensor_msgs/CameraInfo.k`` (9 values or [3, 3]; pixel (col, row) centred at (col, row))
    -> the [3, 3] K of this module (centred at (col + 0.5, row + 0.5)), for the image resized by
    ``scale_x`` / ``scale_y`` (exact in this convention: every entry of a row scales)."""
    K = np.array(k, dtype=np.float64).reshape(3, 3)
    K[0, 2] += 0.5
    K[1, 2] += 0.5
    K[0, :] *= scale_x
    K[1, :] *= scale_y
    return K


def k_to_camera_info(K: _ArrayLike) -> np.ndarray:
    """The [3, 3] K of this module -> the K of ``sensor_msgs/CameraInfo`` (inverse of
    :func:`k_from_camera_info` at scale 1)."""
    K = np.array(K.detach().cpu() if isinstance(K, torch.Tensor) else K, dtype=np.float64).reshape(3, 3)
    K[0, 2] -= 0.5
    K[1, 2] -= 0.5
    return K


def _as_tensor(x: _ArrayLike, dtype=None, device=None) -> torch.Tensor:
    if isinstance(x, torch.Tensor):
        t = x
    else:
        t = torch.as_tensor(np.asarray(x))
    if dtype is None:
        dtype = t.dtype if t.is_floating_point() else torch.float32
    return t.to(dtype=dtype, device=device)


@dataclass
class Cameras:
    """C pinhole cameras sharing (width, height). See module docstring."""

    K: torch.Tensor
    world_to_cam: torch.Tensor
    width: int
    height: int
    names: Optional[list[str]] = None

    def __post_init__(self) -> None:
        if self.K.ndim == 2:
            self.K = self.K[None]
        if self.world_to_cam.ndim == 2:
            self.world_to_cam = self.world_to_cam[None]
        if self.K.ndim != 3 or self.K.shape[1:] != (3, 3):
            raise ValueError(f"Cameras.K must be [C, 3, 3], got {list(self.K.shape)}")
        if self.world_to_cam.ndim != 3 or self.world_to_cam.shape[1:] != (4, 4):
            raise ValueError(
                f"Cameras.world_to_cam must be [C, 4, 4], got {list(self.world_to_cam.shape)}"
            )
        if self.K.shape[0] != self.world_to_cam.shape[0]:
            raise ValueError(
                f"Cameras.K has {self.K.shape[0]} cameras but world_to_cam has "
                f"{self.world_to_cam.shape[0]}"
            )
        if not self.K.is_floating_point() or not self.world_to_cam.is_floating_point():
            raise ValueError("Cameras.K and Cameras.world_to_cam must be floating point")
        if self.K.device != self.world_to_cam.device:
            raise ValueError("Cameras.K and Cameras.world_to_cam must be on the same device")
        self.width = int(self.width)
        self.height = int(self.height)
        if self.width <= 0 or self.height <= 0:
            raise ValueError(f"Cameras image size must be positive, got {self.width}x{self.height}")
        if self.names is not None:
            self.names = [str(n) for n in self.names]
            if len(self.names) != self.K.shape[0]:
                raise ValueError(
                    f"Cameras.names has {len(self.names)} entries for {self.K.shape[0]} cameras"
                )
        if (self.K[:, 0, 0] <= 0).any() or (self.K[:, 1, 1] <= 0).any():
            raise ValueError("Cameras.K focal lengths (K[:,0,0], K[:,1,1]) must be > 0")

    # ------------------------------------------------------------- factories
    @staticmethod
    def from_cam_to_world(
        K: _ArrayLike,
        cam_to_world: _ArrayLike,
        width: int,
        height: int,
        names: Optional[Sequence[str]] = None,
        dtype: torch.dtype = torch.float32,
        device=None,
    ) -> "Cameras":
        """Build from intrinsics [C,3,3] and camera-to-world poses [C,4,4] (or [C,3,4]).

        Poses are inverted in float64 (rigid inverse R^T, -R^T t).
        """
        K_t = _as_tensor(K, torch.float64)
        c2w = _as_tensor(cam_to_world, torch.float64)
        if c2w.ndim == 2:
            c2w = c2w[None]
        if K_t.ndim == 2:
            K_t = K_t[None]
        if c2w.ndim != 3 or c2w.shape[1:] not in ((4, 4), (3, 4)):
            raise ValueError(f"cam_to_world must be [C, 4, 4] or [C, 3, 4], got {list(c2w.shape)}")
        R = c2w[:, :3, :3]
        t = c2w[:, :3, 3]
        w2c = torch.zeros(c2w.shape[0], 4, 4, dtype=torch.float64, device=c2w.device)
        w2c[:, :3, :3] = R.transpose(1, 2)
        w2c[:, :3, 3] = -(R.transpose(1, 2) @ t[:, :, None])[:, :, 0]
        w2c[:, 3, 3] = 1.0
        return Cameras(
            K=K_t.to(dtype=dtype, device=device),
            world_to_cam=w2c.to(dtype=dtype, device=device),
            width=width,
            height=height,
            names=list(names) if names is not None else None,
        )

    @staticmethod
    def from_rt(
        K: _ArrayLike,
        R_c2w: _ArrayLike,
        t_c2w: _ArrayLike,
        width: int,
        height: int,
        names: Optional[Sequence[str]] = None,
        dtype: torch.dtype = torch.float32,
    ) -> "Cameras":
        """Build from K [C,3,3], camera-to-world rotations [C,3,3] and translations [C,3]
        (the ``intr_list.npy`` / ``R_list.npy`` / ``t_list.npy`` layout of the rope data)."""
        R = _as_tensor(R_c2w, torch.float64)
        t = _as_tensor(t_c2w, torch.float64)
        if R.ndim == 2:
            R = R[None]
        if t.ndim == 1:
            t = t[None]
        if R.shape[1:] != (3, 3) or t.shape[1:] != (3,) or R.shape[0] != t.shape[0]:
            raise ValueError(f"R must be [C,3,3] and t [C,3], got {list(R.shape)} and {list(t.shape)}")
        c2w = torch.cat([R, t[:, :, None]], dim=2)
        return Cameras.from_cam_to_world(K, c2w, width, height, names, dtype=dtype)

    # ------------------------------------------------------------------ basics
    def __len__(self) -> int:
        return int(self.K.shape[0])

    @property
    def device(self) -> torch.device:
        return self.K.device

    @property
    def dtype(self) -> torch.dtype:
        return self.K.dtype

    def to(self, device=None, dtype: Optional[torch.dtype] = None) -> "Cameras":
        return Cameras(
            K=self.K.to(device=device, dtype=dtype),
            world_to_cam=self.world_to_cam.to(device=device, dtype=dtype),
            width=self.width,
            height=self.height,
            names=None if self.names is None else list(self.names),
        )

    def select(self, idx) -> "Cameras":
        """Subset by an int, a slice, a list of ints, an index tensor or a bool mask over C."""
        if isinstance(idx, int):
            idx = [idx]
        if isinstance(idx, slice):
            ids = list(range(len(self)))[idx]
        elif isinstance(idx, torch.Tensor) and idx.dtype == torch.bool:
            ids = torch.nonzero(idx.cpu(), as_tuple=False)[:, 0].tolist()
        else:
            ids = [int(i) for i in (idx.tolist() if isinstance(idx, torch.Tensor) else idx)]
        for i in ids:
            if not -len(self) <= i < len(self):
                raise IndexError(f"camera index {i} out of range for {len(self)} cameras")
        index = torch.as_tensor(ids, dtype=torch.long, device=self.device)
        return Cameras(
            K=self.K[index],
            world_to_cam=self.world_to_cam[index],
            width=self.width,
            height=self.height,
            names=None if self.names is None else [self.names[i] for i in ids],
        )

    def scaled(self, factor: float) -> "Cameras":
        """Cameras for an image resized by ``factor`` (e.g. 0.5 for 640x480 -> 320x240).

        The new size is ``round(width * factor)`` x ``round(height * factor)``; the
        intrinsics are scaled per axis by the actual size ratio so that the image
        borders keep their meaning (pixel-edge convention: u' = u * sx).
        """
        if factor <= 0:
            raise ValueError(f"scale factor must be > 0, got {factor}")
        w = max(1, int(round(self.width * factor)))
        h = max(1, int(round(self.height * factor)))
        sx = w / self.width
        sy = h / self.height
        K = self.K.clone()
        K[:, 0, :] = K[:, 0, :] * sx
        K[:, 1, :] = K[:, 1, :] * sy
        return Cameras(K=K, world_to_cam=self.world_to_cam.clone(), width=w, height=h,
                       names=None if self.names is None else list(self.names))

    def cam_to_world(self) -> torch.Tensor:
        """Camera-to-world poses [C, 4, 4] (rigid inverse of world_to_cam)."""
        R = self.world_to_cam[:, :3, :3]
        t = self.world_to_cam[:, :3, 3]
        out = torch.zeros_like(self.world_to_cam)
        out[:, :3, :3] = R.transpose(1, 2)
        out[:, :3, 3] = -(R.transpose(1, 2) @ t[:, :, None])[:, :, 0]
        out[:, 3, 3] = 1.0
        return out

    def centers(self) -> torch.Tensor:
        """Camera centres in world coordinates [C, 3] (= -R^T t)."""
        R = self.world_to_cam[:, :3, :3]
        t = self.world_to_cam[:, :3, 3]
        return -(R.transpose(1, 2) @ t[:, :, None])[:, :, 0]

    def project(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """World points [N, 3] -> (pixels [C, N, 2], camera-frame depth z [C, N])."""
        if points.ndim != 2 or points.shape[1] != 3:
            raise ValueError(f"points must be [N, 3], got {list(points.shape)}")
        R = self.world_to_cam[:, :3, :3].to(points.dtype)
        t = self.world_to_cam[:, :3, 3].to(points.dtype)
        pc = torch.einsum("cij,nj->cni", R, points) + t[:, None, :]
        z = pc[..., 2]
        K = self.K.to(points.dtype)
        u = K[:, None, 0, 0] * pc[..., 0] / z + K[:, None, 0, 2]
        v = K[:, None, 1, 1] * pc[..., 1] / z + K[:, None, 1, 2]
        return torch.stack([u, v], dim=-1), z


def frame_points(
    points: torch.Tensor,
    width: int,
    height: int,
    fov_x_deg: float = 50.0,
    margin: float = 1.15,
    dtype: torch.dtype = torch.float32,
    name: str = "framing",
) -> "Cameras":
    """One camera that looks at the centroid of ``points`` [N, 3] and frames their bounding box.

    The view direction is the world axis along which the axis-aligned bounding box
    is thinnest; the longest box axis runs along the image width, the middle one
    along the height; the distance makes the box fill the image up to ``margin``.
    """
    if points.ndim != 2 or points.shape[1] != 3 or points.shape[0] == 0:
        raise ValueError(f"frame_points: points must be [N>0, 3], got {list(points.shape)}")
    p = points.detach().to("cpu", torch.float64)
    lo, hi = p.min(0).values, p.max(0).values
    ext = (hi - lo).clamp_min(1e-6)
    centroid = p.mean(0)
    order = torch.argsort(ext)  # thin, middle, long
    a_view, a_mid, a_long = (int(i) for i in order)
    f = 0.5 * width / math.tan(math.radians(fov_x_deg) / 2.0)
    # distance from the centroid to the near face, so the box fits both image axes
    half_long = torch.maximum(hi[a_long] - centroid[a_long], centroid[a_long] - lo[a_long])
    half_mid = torch.maximum(hi[a_mid] - centroid[a_mid], centroid[a_mid] - lo[a_mid])
    d = margin * max(float(half_long) * f / (0.5 * width), float(half_mid) * f / (0.5 * height))
    d += float(centroid[a_view] - lo[a_view])
    e_view = torch.zeros(3, dtype=torch.float64)
    e_view[a_view] = 1.0
    up = torch.zeros(3, dtype=torch.float64)
    up[a_mid] = 1.0
    eye = centroid - d * e_view
    K = torch.tensor([[f, 0.0, width / 2.0], [0.0, f, height / 2.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    return Cameras.from_cam_to_world(K, look_at(eye, centroid, up), width, height, [name], dtype=dtype)


def look_at(
    eye: _ArrayLike,
    target: _ArrayLike,
    up: _ArrayLike = (0.0, 0.0, 1.0),
    dtype: torch.dtype = torch.float64,
) -> torch.Tensor:
    """Camera-to-world pose [4, 4] of an OpenCV camera at ``eye`` looking at ``target``.

    Image "up" (-y of the camera) is aligned as well as possible with world ``up``.
    Raises ValueError when the viewing direction is parallel to ``up``.
    """
    eye_t = _as_tensor(eye, torch.float64).reshape(3)
    tgt = _as_tensor(target, torch.float64).reshape(3)
    up_t = _as_tensor(up, torch.float64).reshape(3)
    z = tgt - eye_t
    if z.norm() < 1e-12:
        raise ValueError("look_at: eye and target coincide")
    z = z / z.norm()
    x = torch.linalg.cross(z, up_t)  # camera x (right) = forward x up (y = -up)
    if x.norm() < 1e-9:
        raise ValueError("look_at: viewing direction is parallel to the up vector")
    x = x / x.norm()
    y = torch.linalg.cross(z, x)  # camera y (down)
    pose = torch.eye(4, dtype=torch.float64)
    pose[:3, 0] = x
    pose[:3, 1] = y
    pose[:3, 2] = z
    pose[:3, 3] = eye_t
    return pose.to(dtype)
