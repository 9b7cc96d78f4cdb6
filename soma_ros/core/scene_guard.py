"""Checks on scenes that arrive from outside: where a file may be read from, how big
it may be, what a splat cloud's layout must be, and what is physically plausible.

Everything here runs before a new scene touches the simulator, and the size
checks run before anything proportional to the announced size is allocated:

* :class:`ScenePathPolicy` opens a scene file only when its real path (symlinks
  resolved) lies inside one of the allowed folders. Every refusal for "missing",
  "not allowed" and "not a scene file" is the same :data:`GENERIC_REFUSAL`, so a
  client cannot tell them apart (no existence oracle), and nothing about a file
  outside the folders (content, header lines, size) is ever reported.
* :func:`check_cloud_layout` checks a ``sensor_msgs/PointCloud2``-shaped object
  (rclpy message or not) in O(number of fields): point count against the limit,
  data length against ``width * height * point_step``, every splat field FLOAT32
  with count 1, no two fields sharing bytes.
* :func:`check_physical` checks a decoded scene against the scene the node
  started with (:class:`SceneExtent`): bounding radius, centre offset and the
  largest splat standard deviation, each relative to that scene.

:class:`SceneLimits` holds the bounds; the node exposes each as a parameter.
No rclpy here.
"""

from __future__ import annotations

import os
import stat
from dataclasses import dataclass
from pathlib import Path
from typing import Any, BinaryIO, Optional, Sequence

import numpy as np
import torch

from .splats import Splats

__all__ = ["SceneLimits", "SceneRefused", "ScenePathPolicy", "SceneExtent", "GENERIC_REFUSAL",
           "check_cloud_layout", "check_physical", "read_scene_file"]

#: The one answer to a path that is missing, outside the allowed folders, or not a scene file.
GENERIC_REFUSAL = "no scene this node may read at that path (allowed: the node's scene_dirs, .ply / .splat files or scene bundle folders)"

_SCENE_SUFFIXES = (".ply", ".splat")
_FLOAT32 = 7  # sensor_msgs/PointField.FLOAT32
_DATATYPE_SIZE = {1: 1, 2: 1, 3: 2, 4: 2, 5: 4, 6: 4, 7: 4, 8: 8}


class SceneRefused(ValueError):
    """A scene that is not taken; the message is safe to send back to the requester."""


@dataclass(frozen=True)
class SceneLimits:
    """Bounds on a scene that arrives at run time.

    ``max_splats``: most splats (checked from the header or the message before reading).
    ``max_file_bytes``: largest scene file. ``max_scale_ratio``: the largest splat standard
    deviation allowed, as a fraction of the starting scene's diameter. ``max_extent_ratio``:
    the largest bounding radius, as a multiple of the starting scene's. ``max_offset_m``: how
    far the new scene's centre may lie beyond the starting scene's bounding sphere, metres.
    """

    max_splats: int = 200_000
    max_file_bytes: int = 256 * 2**20
    max_scale_ratio: float = 0.05
    max_extent_ratio: float = 10.0
    max_offset_m: float = 2.0

    def __post_init__(self) -> None:
        if self.max_splats < 1 or self.max_file_bytes < 1:
            raise ValueError(f"SceneLimits: max_splats and max_file_bytes must be >= 1, got {self.max_splats}, "
                             f"{self.max_file_bytes}")
        if not (self.max_scale_ratio > 0 and self.max_extent_ratio > 0 and self.max_offset_m >= 0):
            raise ValueError("SceneLimits: max_scale_ratio and max_extent_ratio must be > 0, max_offset_m >= 0")


# ------------------------------------------------------------------ file system
class ScenePathPolicy:
    """Which scene files may be read: real paths inside ``dirs`` only.

    ``dirs`` are resolved once (symlinks followed); folders that do not exist are kept and
    allow nothing until they do.
    """

    def __init__(self, dirs: Sequence[str | os.PathLike]) -> None:
        self.dirs = [Path(os.path.expanduser(str(d))).resolve() for d in dirs if str(d)]

    def allowed(self, real: Path) -> bool:
        return any(real == d or real.is_relative_to(d) for d in self.dirs)

    def _real(self, p: Path) -> Path:
        try:
            real = p.resolve(strict=True)
        except (OSError, RuntimeError):  # missing, a symlink loop, no permission
            raise SceneRefused(GENERIC_REFUSAL) from None
        if not self.allowed(real):
            raise SceneRefused(GENERIC_REFUSAL)
        return real

    def open(self, path: str, limits: SceneLimits) -> tuple[Path, BinaryIO]:
        """Open the scene file at absolute ``path`` (a .ply / .splat file or a scene bundle folder
        holding splats.ply); returns (real path, open binary file). Raises :class:`SceneRefused`."""
        if not path or not os.path.isabs(path):
            raise SceneRefused("ply_path must be an absolute path")
        real = self._real(Path(path))
        if real.is_dir():
            real = self._real(real / "splats.ply")
        if real.suffix.lower() not in _SCENE_SUFFIXES:
            raise SceneRefused(GENERIC_REFUSAL)
        try:  # O_NONBLOCK: a FIFO must not hang the open; O_NOFOLLOW: no symlink swapped in since
            fd = os.open(real, os.O_RDONLY | os.O_NONBLOCK | os.O_NOFOLLOW | getattr(os, "O_CLOEXEC", 0))
        except OSError:
            raise SceneRefused(GENERIC_REFUSAL) from None
        try:
            st = os.fstat(fd)
            if not stat.S_ISREG(st.st_mode):
                raise SceneRefused(GENERIC_REFUSAL)
            if st.st_size > limits.max_file_bytes:
                raise SceneRefused(f"{real.name}: {st.st_size} bytes, more than max_file_bytes "
                                   f"({limits.max_file_bytes})")
            os.set_blocking(fd, True)
            return real, os.fdopen(fd, "rb")
        except BaseException:
            os.close(fd)
            raise


def read_scene_file(path: str, policy: ScenePathPolicy, limits: SceneLimits) -> Splats:
    """A scene file read through ``policy`` with the size limits (header checked before data).

    Errors of a file inside the allowed folders name the problem; anything else is
    :data:`GENERIC_REFUSAL`."""
    from .ply import PlyError, load_splats

    real, f = policy.open(path, limits)
    with f:
        try:
            s = load_splats(real, max_splats=limits.max_splats, file=f)
        except PlyError as exc:
            raise SceneRefused(str(exc).replace(str(real), real.name)) from None
    return s


# ------------------------------------------------------------------ messages
def check_cloud_layout(cloud: Any, limits: SceneLimits, required: Sequence[str],
                       float32: Sequence[str] = ()) -> int:
    """Check a PointCloud2-shaped object's sizes and field layout without touching its data;
    returns the point count. ``required``: the fields that must be present; they and any of
    ``float32`` that are present must be FLOAT32 with count 1."""
    w, h = int(cloud.width), int(cloud.height)
    n = w * h
    if n == 0:
        raise SceneRefused("the splat cloud has 0 points")
    if n > limits.max_splats:
        raise SceneRefused(f"the splat cloud has {n} points, more than max_splats ({limits.max_splats})")
    if getattr(cloud, "is_bigendian", False):
        raise SceneRefused("big-endian PointCloud2 is not supported")
    step, row = int(cloud.point_step), int(cloud.row_step)
    if step <= 0:
        raise SceneRefused(f"point_step must be > 0, got {step}")
    if row not in (0, step * w):
        raise SceneRefused(f"row_step {row} is not width * point_step ({step * w}): row padding is not supported")
    size = len(cloud.data)
    if size != n * step:
        raise SceneRefused(f"data holds {size} bytes, expected width * height * point_step = {n * step}")
    spans = []
    names = [str(f.name) for f in cloud.fields]
    if len(set(names)) != len(names):
        raise SceneRefused("the splat cloud declares a field twice")
    for f in cloud.fields:
        dt, count, off = int(f.datatype), int(f.count), int(f.offset)
        if dt not in _DATATYPE_SIZE:
            raise SceneRefused(f"field '{f.name}' has unknown datatype {dt}")
        if (f.name in required or f.name in float32) and (dt != _FLOAT32 or count != 1):
            raise SceneRefused(f"field '{f.name}' must be FLOAT32 (7) with count 1, got datatype {dt} count {count}")
        end = off + _DATATYPE_SIZE[dt] * max(count, 1)
        if off < 0 or end > step:
            raise SceneRefused(f"field '{f.name}' (bytes {off}..{end}) overruns point_step {step}")
        spans.append((off, end, str(f.name)))
    spans.sort()
    for (a0, a1, an), (b0, b1, bn) in zip(spans, spans[1:]):
        if b0 < a1:
            raise SceneRefused(f"fields '{an}' and '{bn}' overlap (bytes {a0}..{a1} and {b0}..{b1})")
    missing = [r for r in required if r not in names]
    if missing:
        raise SceneRefused(f"the splat cloud lacks required fields: {', '.join(missing)}")
    return n


# ------------------------------------------------------------------ physics
@dataclass(frozen=True)
class SceneExtent:
    """Bounding sphere of a scene: centre [3] (mean of the splat centres) and radius, metres."""

    center: np.ndarray
    radius: float

    @staticmethod
    def of(splats: Splats) -> "SceneExtent":
        m = splats.means.detach().to("cpu", torch.float64)
        c = m.mean(dim=0)
        return SceneExtent(c.numpy(), float((m - c).norm(dim=-1).max()) if len(splats) else 0.0)


def check_physical(splats: Splats, reference: SceneExtent, limits: SceneLimits) -> None:
    """Refuse a scene that is not plausible beside the starting scene ``reference``
    (finite values and ranges first, then extent, offset and splat size)."""
    if len(splats) == 0:
        raise SceneRefused("the scene has no splats")
    if len(splats) > limits.max_splats:
        raise SceneRefused(f"the scene has {len(splats)} splats, more than max_splats ({limits.max_splats})")
    try:
        splats.validate()
    except ValueError as exc:
        raise SceneRefused(str(exc)) from None
    ref_r = max(reference.radius, 1e-3)
    ext = SceneExtent.of(splats)
    if ext.radius > limits.max_extent_ratio * ref_r:
        raise SceneRefused(f"the scene's bounding radius {ext.radius:.3g} m is more than max_extent_ratio "
                           f"({limits.max_extent_ratio:g}) times the starting scene's ({ref_r:.3g} m)")
    off = float(np.linalg.norm(ext.center - reference.center))
    if off > ref_r + limits.max_offset_m:
        raise SceneRefused(f"the scene's centre is {off:.3g} m from the starting scene's, more than its radius "
                           f"({ref_r:.3g} m) + max_offset_m ({limits.max_offset_m:g} m)")
    cap = limits.max_scale_ratio * 2.0 * ref_r
    big = splats.scales.detach().max(dim=-1).values
    n_big = int((big > cap).sum())
    if n_big:
        raise SceneRefused(f"{n_big} splats have a standard deviation above {cap:.3g} m (max_scale_ratio "
                           f"{limits.max_scale_ratio:g} of the starting scene's diameter); the largest is "
                           f"{float(big.max()):.3g} m")
