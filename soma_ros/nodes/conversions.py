"""numpy/torch <-> rclpy message conversions (sensor_msgs, soma_msgs).

Kept free of node logic so it can be unit-tested with plain messages.
"""

from __future__ import annotations

import array
from typing import Optional, Sequence

import numpy as np
from builtin_interfaces.msg import Time
from sensor_msgs.msg import CameraInfo, Image, PointCloud2, PointField
from std_msgs.msg import Header

from ..core.cameras import k_to_camera_info
from ..core.cloud_layout import POINT_STEP, cloud_to_splats, splat_field_specs, splats_to_records
from ..core.splats import Splats


def uint8_field(buf: np.ndarray) -> array.array:
    """The bytes of a C-contiguous array as ``array.array('B')``, for a message's ``uint8[]`` field.

    One memcpy. Assigning ``bytes`` instead makes the generated rclpy setter check every
    element in Python (two generator passes under the GIL: milliseconds per image and
    per cloud, which stall every other thread of the node).
    """
    out = array.array("B")
    out.frombytes(memoryview(np.ascontiguousarray(buf)).cast("B"))
    return out


def stamp_from_ns(ns: int) -> Time:
    return Time(sec=int(ns // 1_000_000_000), nanosec=int(ns % 1_000_000_000))


def ns_from_stamp(stamp: Time) -> int:
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def matrix_to_tf(T: np.ndarray, parent: str, child: str, stamp: Optional[Time] = None):
    """[4, 4] pose of `child` in `parent` -> geometry_msgs/TransformStamped."""
    import torch
    from geometry_msgs.msg import TransformStamped

    from ..core.geometry import rotmat_to_quat

    q = rotmat_to_quat(torch.as_tensor(np.asarray(T)[:3, :3], dtype=torch.float64)).numpy()
    tf = TransformStamped()
    tf.header.stamp = stamp or Time()
    tf.header.frame_id = parent
    tf.child_frame_id = child
    tf.transform.translation.x, tf.transform.translation.y, tf.transform.translation.z = (float(v) for v in T[:3, 3])
    r = tf.transform.rotation
    r.w, r.x, r.y, r.z = (float(v) for v in q)
    return tf


def splats_to_cloud(splats: Splats, frame_id: str, stamp: Optional[Time] = None) -> PointCloud2:
    """Splats -> sensor_msgs/PointCloud2 in the soma_msgs splat layout (with packed rgb)."""
    rec = splats_to_records(splats)
    msg = PointCloud2()
    msg.header = Header(frame_id=frame_id, stamp=stamp or Time())
    msg.height = 1
    msg.width = int(rec.shape[0])
    msg.fields = [PointField(name=f.name, offset=f.offset, datatype=f.datatype, count=f.count) for f in splat_field_specs()]
    msg.is_bigendian = False
    msg.point_step = POINT_STEP
    msg.row_step = POINT_STEP * msg.width
    msg.is_dense = True
    msg.data = uint8_field(rec)
    return msg


def cloud_to_splats_msg(msg: PointCloud2, device: str = "cpu") -> Splats:
    """sensor_msgs/PointCloud2 in the splat layout -> validated Splats (ValueError names the problem)."""
    return cloud_to_splats(msg, device=device)


def image_rgb8(rgb: np.ndarray, frame_id: str, stamp: Time) -> Image:
    """uint8 [H, W, 3] -> sensor_msgs/Image rgb8."""
    if rgb.dtype != np.uint8 or rgb.ndim != 3 or rgb.shape[2] != 3:
        raise ValueError(f"rgb8 image must be uint8 [H, W, 3], got {rgb.dtype} {rgb.shape}")
    h, w, _ = rgb.shape
    return Image(header=Header(frame_id=frame_id, stamp=stamp), height=h, width=w, encoding="rgb8",
                 is_bigendian=0, step=3 * w, data=uint8_field(rgb))


def image_depth32(depth_m: np.ndarray, frame_id: str, stamp: Time) -> Image:
    """float32 [H, W] metres -> sensor_msgs/Image 32FC1. A pixel with no surface (depth <= 0,
    as the renderer writes where nothing was drawn, or non-finite) becomes NaN: REP 118's
    "no return", which depth_image_proc and PCL skip (a 0 would be a point at the camera);
    +inf ("too far" in REP 118) stays."""
    if depth_m.ndim != 2:
        raise ValueError(f"depth image must be [H, W], got {depth_m.shape}")
    d = np.array(depth_m, dtype=np.float32, order="C")
    d[~(d > 0)] = np.nan
    h, w = d.shape
    return Image(header=Header(frame_id=frame_id, stamp=stamp), height=h, width=w, encoding="32FC1",
                 is_bigendian=0, step=4 * w, data=uint8_field(d))


def camera_info(K: np.ndarray, width: int, height: int, frame_id: str, stamp: Time) -> CameraInfo:
    """Pinhole intrinsics [3, 3] of :mod:`soma_ros.core.cameras` (pixel centres at +0.5) ->
    sensor_msgs/CameraInfo (pixel centres at integers: cx, cy half a pixel smaller; plumb_bob,
    no distortion)."""
    K = k_to_camera_info(K)
    P = np.zeros((3, 4))
    P[:, :3] = K
    return CameraInfo(header=Header(frame_id=frame_id, stamp=stamp), width=int(width), height=int(height),
                      distortion_model="plumb_bob", d=[0.0] * 5, k=K.ravel().tolist(),
                      r=np.eye(3).ravel().tolist(), p=P.ravel().tolist())


def joint_positions(names: Sequence[str], positions: Sequence[float], wanted: Sequence[str]) -> np.ndarray:
    """Positions of `wanted` joints from a JointState's (names, positions); ValueError names the problem."""
    if len(names) != len(positions):
        raise ValueError(f"JointState has {len(names)} names but {len(positions)} positions")
    index = {n: i for i, n in enumerate(names)}
    missing = [w for w in wanted if w not in index]
    if missing:
        raise ValueError(f"JointState lacks joints: {', '.join(missing)}")
    q = np.array([positions[index[w]] for w in wanted], dtype=np.float64)
    if not np.all(np.isfinite(q)):
        bad = [w for w, v in zip(wanted, q) if not np.isfinite(v)]
        raise ValueError(f"JointState has non-finite positions for: {', '.join(bad)}")
    return q
