"""EVALUATION-ONLY ground truth: the reference world's object points.

The MuJoCo reference world records the deformable object's true vertices on
``/world/object_points`` (``sensor_msgs/PointCloud2``, float32 x y z in the
``world`` frame, one message per frame, stamped like the camera frames).
Training code must never read them (:data:`soma_ros.data.bags.FORBIDDEN_TOPICS`);
this module is the one place that does, and only :mod:`soma_ros.evaluation.evaluate`
imports it, to score rollouts with the 3D Chamfer distance.

``read_ground_truth_points(bag)`` returns ``[T, M, 3]`` float32, one row per
frame of the episode's frame clock (the first camera's colour stamps, as
:func:`soma_ros.data.bags.read_episode` uses), matched by nearest stamp.
"""

from __future__ import annotations

from pathlib import Path
from typing import Optional, Sequence

import numpy as np
from soma_ros.core.errors import DataError

__all__ = ["GROUND_TRUTH_TOPIC", "GroundTruthError", "read_ground_truth_points", "decode_xyz_cloud"]

#: the evaluation-only topic (same name as soma_ros.world.OBJECT_POINTS_TOPIC)
GROUND_TRUTH_TOPIC = "/world/object_points"

_FLOAT32 = 7
_FLOAT64 = 8


class GroundTruthError(DataError):
    """A bag without usable ground-truth object points (one-line reason)."""


def decode_xyz_cloud(msg, topic: str = GROUND_TRUTH_TOPIC) -> np.ndarray:
    """sensor_msgs/PointCloud2 with float32/float64 fields x, y, z -> [N, 3] float32."""
    fields = {f.name: f for f in msg.fields}
    for name in ("x", "y", "z"):
        if name not in fields:
            raise GroundTruthError(f"{topic}: PointCloud2 has no '{name}' field (fields: {sorted(fields)})")
        if int(fields[name].datatype) not in (_FLOAT32, _FLOAT64):
            raise GroundTruthError(f"{topic}: field '{name}' is not float32/float64 (datatype {fields[name].datatype})")
    n = int(msg.width) * int(msg.height)
    step = int(msg.point_step)
    buf = np.asarray(msg.data, dtype=np.uint8)
    if buf.size < n * step:
        raise GroundTruthError(f"{topic}: PointCloud2 buffer holds {buf.size} bytes for {n} points of {step} bytes")
    rows = buf[: n * step].reshape(n, step)
    endian = ">" if bool(msg.is_bigendian) else "<"
    cols = []
    for name in ("x", "y", "z"):
        f = fields[name]
        dt = np.dtype(f"{endian}f4") if int(f.datatype) == _FLOAT32 else np.dtype(f"{endian}f8")
        off = int(f.offset)
        cols.append(np.ascontiguousarray(rows[:, off: off + dt.itemsize]).view(dt).reshape(n).astype(np.float32))
    pts = np.stack(cols, axis=-1)
    if not np.isfinite(pts).all():
        raise GroundTruthError(f"{topic}: PointCloud2 has non-finite points")
    return pts


def _stamp_ns(header) -> int:
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


def read_ground_truth_points(
    bag: str | Path,
    stamps_ns: Optional[Sequence[int]] = None,
    camera: Optional[str] = None,
    sync_tolerance_ms: float = 20.0,
    frame: str = "world",
) -> np.ndarray:
    """Ground-truth object points of every frame of an episode bag: [T, M, 3] float32 (metres, ``frame``).

    ``stamps_ns``: the frame clock to align to (e.g. ``EpisodeData.stamps_ns``); default: the colour
    stamps of ``camera`` (default: the alphabetically first ``/<cam>/color/image_raw``, the clock of
    :func:`soma_ros.data.bags.read_episode`). Every frame takes the cloud with the nearest stamp, which must
    lie within ``sync_tolerance_ms``. Raises :class:`GroundTruthError` if the bag has no ground truth
    (e.g. a real recording), if the point count changes, or if the clouds are not in ``frame``.
    """
    from rosbags.highlevel import AnyReader

    from soma_ros.bagtypes import typestore

    bag = Path(bag)
    if not bag.exists():
        raise FileNotFoundError(f"bag not found: {bag}")
    with AnyReader([bag], default_typestore=typestore()) as reader:
        by_topic = {c.topic: c for c in reader.connections}
        if GROUND_TRUTH_TOPIC not in by_topic:
            raise GroundTruthError(f"{bag.name}: no {GROUND_TRUTH_TOPIC} (ground truth exists only for reference-world bags)")
        conns = [by_topic[GROUND_TRUTH_TOPIC]]
        clock_topic = None
        if stamps_ns is None:
            cams = sorted(t[1: -len("/color/image_raw")] for t in by_topic if t.endswith("/color/image_raw"))
            if camera is not None:
                if camera not in cams:
                    raise GroundTruthError(f"{bag.name}: no camera '{camera}' (cameras: {', '.join(cams)})")
                cams = [camera]
            if not cams:
                raise GroundTruthError(f"{bag.name}: no /<cam>/color/image_raw topic to take the frame clock from")
            clock_topic = f"/{cams[0]}/color/image_raw"
        clouds: list[tuple[int, np.ndarray]] = []
        clock: list[int] = []
        for conn, _t, data in reader.messages(connections=conns):
            msg = reader.deserialize(data, conn.msgtype)
            if msg.header.frame_id and msg.header.frame_id != frame:
                raise GroundTruthError(f"{bag.name}: {GROUND_TRUTH_TOPIC} is in '{msg.header.frame_id}', expected '{frame}'")
            clouds.append((_stamp_ns(msg.header), decode_xyz_cloud(msg)))
        if clock_topic is not None:
            # only the headers are needed: rosbags deserialises the whole image, which is cheap at these sizes
            for conn, _t, data in reader.messages(connections=[by_topic[clock_topic]]):
                clock.append(_stamp_ns(reader.deserialize(data, conn.msgtype).header))
    if not clouds:
        raise GroundTruthError(f"{bag.name}: {GROUND_TRUTH_TOPIC} is empty")
    clouds.sort(key=lambda c: c[0])
    sizes = {c[1].shape[0] for c in clouds}
    if len(sizes) != 1:
        raise GroundTruthError(f"{bag.name}: {GROUND_TRUTH_TOPIC} changes its point count ({sorted(sizes)})")
    frames = np.asarray(sorted(clock) if stamps_ns is None else list(stamps_ns), dtype=np.int64)
    if frames.size == 0:
        raise GroundTruthError(f"{bag.name}: no frame stamps to align the ground truth to")
    src = np.asarray([c[0] for c in clouds], dtype=np.int64)
    idx = np.clip(np.searchsorted(src, frames), 0, len(src) - 1)
    lo = np.clip(idx - 1, 0, len(src) - 1)
    pick = np.where(np.abs(src[lo] - frames) <= np.abs(src[idx] - frames), lo, idx)
    err = np.abs(src[pick] - frames)
    tol = int(sync_tolerance_ms * 1e6)
    if (err > tol).any():
        raise GroundTruthError(
            f"{bag.name}: {GROUND_TRUTH_TOPIC} has no cloud within {sync_tolerance_ms:.0f} ms of a frame "
            f"(worst {err.max() / 1e6:.1f} ms)"
        )
    out = np.stack([clouds[i][1] for i in pick]).astype(np.float32)
    assert out.ndim == 3 and out.shape[0] == frames.size and out.shape[2] == 3
    return out
