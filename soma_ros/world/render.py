"""Offscreen rendering of the three cameras: RGB, metric depth, object and robot masks.

Two passes per camera and frame: a lit colour pass, and a segmentation pass
(flat ID colours) whose depth buffer gives the metric depth. MuJoCo renders
with a reversed-Z depth buffer (``mjDEPTH_ZEROFAR``): window depth ``w`` is 1
at the near plane and 0 at the far plane, so the distance along the optical
axis is ``z = d' / (w + c')`` with ``c = -(f + n) / (f - n)``,
``d = -2 f n / (f - n)``, ``c' = -(c + 1) / 2`` and ``d' = -d / 2``.

Intrinsics are those of an ideal pinhole with square pixels:
``fx = fy = (H / 2) / tan(fovy / 2)``, ``cx = (W - 1) / 2``, ``cy = (H - 1) / 2``
(pixel centres at integer coordinates, as in OpenCV and ROS).

Shapes: ``rgb`` [H, W, 3] uint8, ``depth_mm`` [H, W] uint16 (millimetres along
the optical axis, 0 = no depth), ``object_mask``/``robot_mask`` [H, W] uint8
(255 = object / robot).
"""

from __future__ import annotations

import os
from dataclasses import dataclass

if "MUJOCO_GL" not in os.environ:  # CPU offscreen rendering (Mesa EGL); set before mujoco loads GL
    os.environ["MUJOCO_GL"] = "egl"

import mujoco  # noqa: E402
import numpy as np  # noqa: E402

from .scene import CAMERA_NAMES, Scene  # noqa: E402

__all__ = ["CameraFrame", "CameraRig", "intrinsics"]


def intrinsics(width: int, height: int, fovy_deg: float) -> np.ndarray:
    """Pinhole matrix K [3, 3] of a MuJoCo camera rendered at width x height."""
    f = (height / 2.0) / np.tan(np.radians(fovy_deg) / 2.0)
    return np.array([[f, 0.0, (width - 1) / 2.0], [0.0, f, (height - 1) / 2.0], [0.0, 0.0, 1.0]])


@dataclass
class CameraFrame:
    rgb: np.ndarray
    depth_mm: np.ndarray
    object_mask: np.ndarray
    robot_mask: np.ndarray


class CameraRig:
    """Renders every camera of a :class:`Scene` at one resolution. Call :meth:`close` when done."""

    def __init__(self, scene: Scene, width: int, height: int) -> None:
        m = scene.model
        if width > m.vis.global_.offwidth or height > m.vis.global_.offheight:
            raise ValueError(f"image {width}x{height} exceeds the model's offscreen buffer")
        self.scene = scene
        self.width, self.height = width, height
        self._gl = self._con = None
        try:
            self._gl = mujoco.GLContext(width, height)
            self._gl.make_current()
            self._con = mujoco.MjrContext(m, mujoco.mjtFontScale.mjFONTSCALE_100.value)
        except Exception as exc:  # no usable GL: one clear line instead of a backend traceback
            self.close()
            backend = os.environ.get("MUJOCO_GL", "")
            raise RuntimeError(
                f"offscreen rendering unavailable with MUJOCO_GL={backend} ({exc.__class__.__name__}: {exc}); "
                "install Mesa EGL (libegl1 libgl1-mesa-dri) or set MUJOCO_GL=osmesa with libosmesa6"
            ) from None
        mujoco.mjr_setBuffer(mujoco.mjtFramebuffer.mjFB_OFFSCREEN.value, self._con)
        self._con.readDepthMap = mujoco.mjtDepthMap.mjDEPTH_ZEROFAR
        self._scn = mujoco.MjvScene(m, maxgeom=4000)
        self._opt = mujoco.MjvOption()
        self._rect = mujoco.MjrRect(0, 0, width, height)
        self._cams = {}
        for name in CAMERA_NAMES:
            c = mujoco.MjvCamera()
            c.type = mujoco.mjtCamera.mjCAMERA_FIXED
            c.fixedcamid = scene.camera_ids[name]
            self._cams[name] = c
        ext = m.stat.extent
        n, f = np.float64(np.float32(m.vis.map.znear * ext)), np.float64(np.float32(m.vis.map.zfar * ext))
        c = -(f + n) / (f - n)
        d = -2.0 * f * n / (f - n)
        self._c, self._d = -0.5 * c - 0.5, -0.5 * d
        self._rgb = np.empty((height, width, 3), np.uint8)
        self._seg = np.empty((height, width, 3), np.uint8)
        self._depth = np.empty((height, width), np.float32)
        self.K = intrinsics(width, height, scene.cfg.cameras.fovy_deg)
        self.depth_min = scene.cfg.cameras.depth_min_m
        self.depth_max = scene.cfg.cameras.depth_max_m
        self._flex_type = int(mujoco.mjtObj.mjOBJ_FLEX)
        self._geom_type = int(mujoco.mjtObj.mjOBJ_GEOM)

    def render(self, data: mujoco.MjData, cam: str) -> CameraFrame:
        """Render one camera (``data`` must be after mj_forward)."""
        m = self.scene.model
        self._gl.make_current()
        mujoco.mjv_updateScene(m, data, self._opt, None, self._cams[cam], mujoco.mjtCatBit.mjCAT_ALL.value, self._scn)
        mujoco.mjr_render(self._rect, self._scn, self._con)
        mujoco.mjr_readPixels(self._rgb, None, self._rect, self._con)
        rgb = np.flipud(self._rgb).copy()
        flags = self._scn.flags.copy()
        try:
            self._scn.flags[mujoco.mjtRndFlag.mjRND_SEGMENT] = True
            self._scn.flags[mujoco.mjtRndFlag.mjRND_IDCOLOR] = True
            mujoco.mjr_render(self._rect, self._scn, self._con)
            mujoco.mjr_readPixels(self._seg, self._depth, self._rect, self._con)
        finally:
            np.copyto(self._scn.flags, flags)
        seg = np.flipud(self._seg).astype(np.int32)
        segid = seg[..., 0] + (seg[..., 1] << 8) + (seg[..., 2] << 16)  # 0 = background, else scene geom + 1
        ng = self._scn.ngeom
        lut_obj = np.zeros(ng + 2, bool)
        lut_rob = np.zeros(ng + 2, bool)
        for g in self._scn.geoms[:ng]:
            if g.segid < 0:
                continue
            if g.objtype == self._flex_type:
                lut_obj[g.segid + 1] = True
            elif g.objtype == self._geom_type and 0 <= g.objid < len(self.scene.robot_geom) and self.scene.robot_geom[g.objid]:
                lut_rob[g.segid + 1] = True
        segid = np.clip(segid, 0, ng + 1)
        w = np.flipud(self._depth).astype(np.float64)
        depth = (self._d / (w + self._c)).astype(np.float32)
        valid = (segid > 0) & (depth >= self.depth_min) & (depth <= self.depth_max)
        depth_mm = np.where(valid, np.round(depth * 1000.0), 0).astype(np.uint16)
        return CameraFrame(
            rgb=rgb,
            depth_mm=depth_mm,
            object_mask=(lut_obj[segid] * 255).astype(np.uint8),
            robot_mask=(lut_rob[segid] * 255).astype(np.uint8),
        )

    def render_all(self, data: mujoco.MjData) -> dict[str, CameraFrame]:
        return {name: self.render(data, name) for name in CAMERA_NAMES}

    def close(self) -> None:
        if self._con is not None:
            self._gl.make_current()
            self._con.free()
            self._con = None
        if self._gl is not None:
            self._gl.free()
            self._gl = None

    def __enter__(self) -> "CameraRig":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
