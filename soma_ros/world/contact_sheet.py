"""A contact sheet PNG per episode, so a person can look at what was recorded.

One row per sampled frame; for each camera four tiles: RGB, depth
(turbo colour map, black = no depth), object mask, robot mask.
"""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

import cv2
import numpy as np

from .render import CameraFrame

__all__ = ["ContactSheet", "sample_frames"]


def sample_frames(n_frames: int, k: int) -> list[int]:
    """``k`` frame indices spread over an episode (first and last included)."""
    k = max(1, min(k, n_frames))
    return sorted(set(np.linspace(0, n_frames - 1, k).round().astype(int).tolist()))


def _depth_tile(depth_mm: np.ndarray) -> np.ndarray:
    valid = depth_mm > 0
    out = np.zeros(depth_mm.shape + (3,), np.uint8)
    if valid.any():
        d = depth_mm[valid].astype(np.float32)
        lo, hi = np.percentile(d, 1), np.percentile(d, 99)
        norm = np.clip((depth_mm.astype(np.float32) - lo) / max(hi - lo, 1.0), 0, 1)
        col = cv2.applyColorMap((255 * (1 - norm)).astype(np.uint8), cv2.COLORMAP_TURBO)[..., ::-1]
        out[valid] = col[valid]
    return out


def _mask_tile(mask: np.ndarray, rgb: np.ndarray, colour: tuple[int, int, int]) -> np.ndarray:
    tile = (rgb.astype(np.float32) * 0.25).astype(np.uint8)
    tile[mask > 0] = colour
    return tile


class ContactSheet:
    """Collects camera frames at chosen indices and writes them as one PNG."""

    def __init__(self, cameras: Sequence[str], frame_indices: Sequence[int], tile_width: int) -> None:
        self.cameras = list(cameras)
        self.indices = list(frame_indices)
        self.tile_width = tile_width
        self.rows: dict[int, list[np.ndarray]] = {}

    def wants(self, index: int) -> bool:
        return index in self.indices

    def add(self, index: int, frames: dict[str, CameraFrame]) -> None:
        tiles = []
        for cam in self.cameras:
            f = frames[cam]
            h, w = f.rgb.shape[:2]
            th = int(round(self.tile_width * h / w))
            for img in (
                f.rgb,
                _depth_tile(f.depth_mm),
                _mask_tile(f.object_mask, f.rgb, (255, 220, 0)),
                _mask_tile(f.robot_mask, f.rgb, (0, 200, 255)),
            ):
                tiles.append(cv2.resize(img, (self.tile_width, th), interpolation=cv2.INTER_AREA))
        self.rows[index] = tiles

    def write(self, path: Path, title: str) -> None:
        if not self.rows:
            raise RuntimeError("contact sheet has no frames")
        first = next(iter(self.rows.values()))
        th, tw = first[0].shape[:2]
        pad, head, left = 2, 34, 56
        n_cols = len(first)
        W = left + n_cols * (tw + pad)
        H = head + len(self.rows) * (th + pad)
        sheet = np.full((H, W, 3), 255, np.uint8)
        font = cv2.FONT_HERSHEY_SIMPLEX
        cv2.putText(sheet, title, (4, 13), font, 0.4, (0, 0, 0), 1, cv2.LINE_AA)
        kinds = ("rgb", "depth", "object", "robot")
        for c, cam in enumerate(self.cameras):
            for k, kind in enumerate(kinds):
                x = left + (c * len(kinds) + k) * (tw + pad)
                cv2.putText(sheet, f"{cam}:{kind}", (x + 2, head - 6), font, 0.33, (0, 0, 0), 1, cv2.LINE_AA)
        for r, idx in enumerate(sorted(self.rows)):
            y = head + r * (th + pad)
            cv2.putText(sheet, f"f{idx}", (4, y + th // 2), font, 0.4, (0, 0, 0), 1, cv2.LINE_AA)
            for c, tile in enumerate(self.rows[idx]):
                x = left + c * (tw + pad)
                sheet[y : y + th, x : x + tw] = tile
        path = Path(path)
        if not cv2.imwrite(str(path), sheet[..., ::-1]):
            raise RuntimeError(f"could not write contact sheet {path}")
