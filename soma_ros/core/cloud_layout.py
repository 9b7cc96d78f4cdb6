"""The soma_msgs Gaussian-splat PointCloud2 layout, as plain numpy.

This module knows the byte layout documented in
``msg_schemas/msg/SplatLayout.msg`` and converts between it and
:class:`~soma_ros.core.splats.Splats`. It never imports rclpy: it works on
anything shaped like a ``sensor_msgs/PointCloud2`` (rclpy messages and
``rosbags`` dataclasses alike: ``fields`` with ``name/offset/datatype/count``,
``height``, ``width``, ``point_step``, ``row_step``, ``is_bigendian``, ``data``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np
import torch

from .splats import Splats, sh_dc_to_rgb

#: sensor_msgs/PointField datatype codes
INT8, UINT8, INT16, UINT16, INT32, UINT32, FLOAT32, FLOAT64 = 1, 2, 3, 4, 5, 6, 7, 8
_NP_OF_DATATYPE = {
    INT8: np.int8, UINT8: np.uint8, INT16: np.int16, UINT16: np.uint16,
    INT32: np.int32, UINT32: np.uint32, FLOAT32: np.float32, FLOAT64: np.float64,
}

SPLAT_FIELDS: tuple[str, ...] = (
    "x", "y", "z",
    "scale_0", "scale_1", "scale_2",
    "rot_w", "rot_x", "rot_y", "rot_z",
    "f_dc_0", "f_dc_1", "f_dc_2",
    "opacity", "rgb", "mass",
)
REQUIRED_FIELDS: tuple[str, ...] = SPLAT_FIELDS[:14]
POINT_STEP = 64
SPLAT_DTYPE = np.dtype({"names": list(SPLAT_FIELDS), "formats": ["<f4"] * 16, "offsets": [4 * i for i in range(16)], "itemsize": POINT_STEP})


@dataclass(frozen=True)
class FieldSpec:
    """One sensor_msgs/PointField: name, byte offset, datatype code, count."""

    name: str
    offset: int
    datatype: int
    count: int = 1


def splat_field_specs() -> list[FieldSpec]:
    """The fields of the splat layout, in order (all FLOAT32, count 1)."""
    return [FieldSpec(n, 4 * i, FLOAT32, 1) for i, n in enumerate(SPLAT_FIELDS)]


def pack_rgb(rgb01: np.ndarray) -> np.ndarray:
    """RGB in [0, 1] [N, 3] -> float32 [N] whose bytes are 0x00RRGGBB (PCL convention)."""
    c = np.clip(np.rint(np.asarray(rgb01, dtype=np.float64) * 255.0), 0, 255).astype(np.uint32)
    packed = (c[:, 0] << 16) | (c[:, 1] << 8) | c[:, 2]
    return packed.astype(np.uint32).view(np.float32)


def unpack_rgb(packed: np.ndarray) -> np.ndarray:
    """float32 [N] packed 0x00RRGGBB -> uint8 [N, 3]."""
    u = np.ascontiguousarray(packed, dtype=np.float32).view(np.uint32)
    return np.stack([(u >> 16) & 255, (u >> 8) & 255, u & 255], axis=-1).astype(np.uint8)


def splats_to_records(splats: Splats) -> np.ndarray:
    """Splats -> structured array [N] in the soma_msgs layout (64 bytes per splat)."""
    n = len(splats)
    rec = np.zeros(n, dtype=SPLAT_DTYPE)

    def np32(t: torch.Tensor) -> np.ndarray:
        return t.detach().to("cpu", torch.float32).numpy()

    means, scales, quats = np32(splats.means), np32(splats.scales), np32(splats.quats)
    sh, op, mass = np32(splats.sh_dc), np32(splats.opacities), np32(splats.mass)
    for i, k in enumerate("xyz"):
        rec[k] = means[:, i]
    for i in range(3):
        rec[f"scale_{i}"] = scales[:, i]
        rec[f"f_dc_{i}"] = sh[:, i]
    for i, k in enumerate(("rot_w", "rot_x", "rot_y", "rot_z")):
        rec[k] = quats[:, i]
    rec["opacity"] = op
    rec["rgb"] = pack_rgb(np32(sh_dc_to_rgb(splats.sh_dc.detach())))
    rec["mass"] = mass
    return rec


def records_to_splats(rec: np.ndarray, device: str | torch.device = "cpu") -> Splats:
    """Structured array with at least REQUIRED_FIELDS -> Splats (validated)."""
    names = rec.dtype.names or ()
    missing = [f for f in REQUIRED_FIELDS if f not in names]
    if missing:
        raise ValueError(f"splat cloud lacks required fields: {', '.join(missing)}")

    def col(*keys: str) -> torch.Tensor:
        a = np.stack([np.asarray(rec[k], dtype=np.float32) for k in keys], axis=-1)
        return torch.from_numpy(np.ascontiguousarray(a)).to(device)

    mass = None
    if "mass" in names:
        m = np.asarray(rec["mass"], dtype=np.float32)
        if m.size and np.all(m > 0):
            mass = torch.from_numpy(m.copy()).to(device)
    s = Splats(
        means=col("x", "y", "z"),
        quats=col("rot_w", "rot_x", "rot_y", "rot_z"),
        scales=col("scale_0", "scale_1", "scale_2"),
        opacities=col("opacity")[:, 0],
        sh_dc=col("f_dc_0", "f_dc_1", "f_dc_2"),
        mass=mass,
    )
    s.validate()
    return s


def cloud_to_records(cloud: Any) -> np.ndarray:
    """A PointCloud2-shaped object -> structured numpy array [N] of its fields.

    Raises ValueError naming the problem (big-endian data, a truncated buffer,
    a field that overruns the point, an unknown datatype).
    """
    if getattr(cloud, "is_bigendian", False):
        raise ValueError("big-endian PointCloud2 is not supported")
    n = int(cloud.width) * int(cloud.height)
    step = int(cloud.point_step)
    data = cloud.data
    buf = np.frombuffer(bytes(data) if not isinstance(data, (bytes, bytearray, np.ndarray)) else data, dtype=np.uint8)
    if n == 0:
        return np.zeros(0, dtype=SPLAT_DTYPE)
    if step <= 0:
        raise ValueError(f"PointCloud2 point_step must be > 0, got {step}")
    row_step = int(getattr(cloud, "row_step", 0) or 0)
    if int(cloud.height) > 1 and row_step and row_step != step * int(cloud.width):
        raise ValueError(f"PointCloud2 row padding is not supported (row_step {row_step} != point_step*width)")
    if buf.size < n * step:
        raise ValueError(f"PointCloud2 data holds {buf.size} bytes, expected {n * step} for {n} points of {step} bytes")
    names, formats, offsets = [], [], []
    for f in cloud.fields:
        dt = _NP_OF_DATATYPE.get(int(f.datatype))
        if dt is None:
            raise ValueError(f"PointCloud2 field '{f.name}' has unknown datatype {f.datatype}")
        count = int(f.count) if int(f.count) > 0 else 1
        size = np.dtype(dt).itemsize * count
        if int(f.offset) + size > step:
            raise ValueError(f"PointCloud2 field '{f.name}' (offset {f.offset}, {size} bytes) overruns point_step {step}")
        names.append(f.name)
        formats.append((np.dtype(dt).newbyteorder("<"), (count,)) if count > 1 else np.dtype(dt).newbyteorder("<"))
        offsets.append(int(f.offset))
    if len(set(names)) != len(names):
        raise ValueError("PointCloud2 has duplicate field names")
    dtype = np.dtype({"names": names, "formats": formats, "offsets": offsets, "itemsize": step})
    return buf[: n * step].view(dtype)


def cloud_to_splats(cloud: Any, device: str | torch.device = "cpu") -> Splats:
    """A splat-layout PointCloud2-shaped object -> validated Splats."""
    rec = cloud_to_records(cloud)
    if rec.size == 0:
        raise ValueError("splat cloud is empty (0 points)")
    return records_to_splats(rec, device=device)


def points_from_cloud(cloud: Any, fields: Sequence[str] = ("x", "y", "z")) -> np.ndarray:
    """float32 [N, len(fields)] from any PointCloud2-shaped object (e.g. xyz)."""
    rec = cloud_to_records(cloud)
    missing = [f for f in fields if rec.dtype.names is None or f not in rec.dtype.names]
    if missing:
        raise ValueError(f"PointCloud2 lacks fields: {', '.join(missing)}")
    return np.stack([np.asarray(rec[f], dtype=np.float32) for f in fields], axis=-1)
