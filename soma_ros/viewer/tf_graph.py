"""The newest transform of every TF edge, and frame poses chained from them (no interpolation).

Enough for a viewer that draws the latest state: each ``child`` keeps its newest
``(parent, T_parent_child)`` from /tf or /tf_static, and :meth:`TfGraph.lookup`
multiplies up the chain to the root. Pure numpy, no ROS.
"""

from __future__ import annotations

import threading
from typing import Optional

import numpy as np

__all__ = ["TfGraph", "transform_to_matrix"]


def transform_to_matrix(tr) -> np.ndarray:
    """geometry_msgs/Transform (any decoder's) -> [4, 4] float64."""
    q = tr.rotation
    w, x, y, z = float(q.w), float(q.x), float(q.y), float(q.z)
    n = np.sqrt(w * w + x * x + y * y + z * z)
    if not np.isfinite(n) or n < 1e-9:
        raise ValueError("transform with an invalid quaternion")
    w, x, y, z = w / n, x / n, y / n, z / n
    T = np.eye(4)
    T[:3, :3] = [[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                 [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                 [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]]
    T[:3, 3] = [float(tr.translation.x), float(tr.translation.y), float(tr.translation.z)]
    return T


class TfGraph:
    def __init__(self) -> None:
        self._edges: dict[str, tuple[str, np.ndarray]] = {}
        self._lock = threading.Lock()

    def add(self, msg) -> int:
        """Take every transform of a TFMessage; returns how many were usable."""
        n = 0
        for t in msg.transforms:
            try:
                T = transform_to_matrix(t.transform)
            except ValueError:
                continue
            with self._lock:
                self._edges[t.child_frame_id] = (t.header.frame_id, T)
            n += 1
        return n

    def frames(self) -> set[str]:
        with self._lock:
            return set(self._edges) | {p for p, _ in self._edges.values()}

    def lookup(self, frame: str, root: str = "world") -> Optional[np.ndarray]:
        """T_root_frame [4, 4], or None when the chain does not reach `root`."""
        T = np.eye(4)
        seen = set()
        with self._lock:
            while frame != root:
                if frame in seen or frame not in self._edges:
                    return None
                seen.add(frame)
                parent, T_pc = self._edges[frame]
                T = T_pc @ T
                frame = parent
        return T
