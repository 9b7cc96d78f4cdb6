"""Pictures of an evaluation for a person: contact sheets and videos (OpenCV).

For every camera three tiles, exactly the images the metrics compare:
**measured** (``GT x object_mask``, robot pixels black), **simulated** (the
rollout rendered over black, robot pixels black) and **error**, the per-pixel
mean absolute colour difference of the two as a heat map (``COLORMAP_INFERNO``,
black = 0, white = ``error_max`` or more). A contact sheet is one PNG per
episode with one row per sampled frame; a video (mp4, ``mp4v``) holds every
scored frame as one row of all cameras.
"""

from __future__ import annotations

from pathlib import Path
from typing import Optional, Sequence

import cv2
import numpy as np
import torch

__all__ = ["comparison_tiles", "EpisodeSheet", "EpisodeVideo", "sample_frames"]

_LABEL_H = 14
_FONT = cv2.FONT_HERSHEY_SIMPLEX


def sample_frames(frames: Sequence[int], k: int) -> list[int]:
    """``k`` of ``frames`` spread evenly (first and last included)."""
    frames = list(frames)
    if not frames or k <= 0:
        return []
    k = min(k, len(frames))
    pick = np.linspace(0, len(frames) - 1, k).round().astype(int)
    return sorted({frames[i] for i in pick})


def _u8(img01: np.ndarray) -> np.ndarray:
    return (np.clip(img01, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


def comparison_tiles(gt_rgb: torch.Tensor, object_mask: torch.Tensor, robot_mask: Optional[torch.Tensor],
                     pred_rgb: torch.Tensor, error_max: float = 0.5) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(measured, simulated, error) uint8 RGB tiles [H, W, 3] of one camera image.

    gt_rgb / pred_rgb [H, W, 3] in [0, 1]; masks [H, W] bool. The error tile maps
    ``mean_c |measured - simulated|`` / error_max through the inferno colour map.
    """
    H, W = object_mask.shape
    if gt_rgb.shape != (H, W, 3) or pred_rgb.shape != (H, W, 3):
        raise ValueError(f"comparison_tiles: images must be [{H}, {W}, 3], got {list(gt_rgb.shape)}, {list(pred_rgb.shape)}")
    keep = torch.ones(H, W) if robot_mask is None else (~robot_mask.bool()).float()
    meas = gt_rgb.float() * (object_mask.float() * keep)[..., None]
    sim = pred_rgb.float() * keep[..., None]
    err = (meas - sim).abs().mean(-1) / max(error_max, 1e-6)
    heat = cv2.applyColorMap(_u8(err.numpy()), cv2.COLORMAP_INFERNO)[..., ::-1]
    return _u8(meas.numpy()), _u8(sim.numpy()), np.ascontiguousarray(heat)


def _label(tile: np.ndarray, text: str) -> np.ndarray:
    bar = np.full((_LABEL_H, tile.shape[1], 3), 255, np.uint8)
    cv2.putText(bar, text, (2, _LABEL_H - 4), _FONT, 0.33, (0, 0, 0), 1, cv2.LINE_AA)
    return np.concatenate([bar, tile], axis=0)


def _scaled(tile: np.ndarray, width: int) -> np.ndarray:
    if tile.shape[1] == width:
        return tile
    h = max(1, int(round(tile.shape[0] * width / tile.shape[1])))
    interp = cv2.INTER_NEAREST if width > tile.shape[1] else cv2.INTER_AREA
    return cv2.resize(tile, (width, h), interpolation=interp)


def _row(tiles_per_camera: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]], tile_width: int,
         labels: bool) -> np.ndarray:
    parts = []
    for cam, (m, s, e) in tiles_per_camera.items():
        for tile, kind in ((m, "measured"), (s, "simulated"), (e, "|error|")):
            t = _scaled(tile, tile_width)
            parts.append(_label(t, f"{cam}: {kind}") if labels else t)
            parts.append(np.full((parts[-1].shape[0], 2, 3), 255, np.uint8))
    return np.concatenate(parts[:-1], axis=1)


class EpisodeSheet:
    """Contact sheet of one episode: rows of chosen frames, three tiles per camera."""

    def __init__(self, title: str, frames: Sequence[int], tile_width: int = 240, error_max: float = 0.5) -> None:
        self.title = title
        self.frames = set(int(f) for f in frames)
        self.tile_width = int(tile_width)
        self.error_max = float(error_max)
        self.rows: list[tuple[int, np.ndarray]] = []

    def wants(self, frame: int) -> bool:
        return int(frame) in self.frames

    def add(self, frame: int, camera_names: Sequence[str], gt_rgb: torch.Tensor, object_mask: torch.Tensor,
            robot_mask: Optional[torch.Tensor], pred_rgb: torch.Tensor, note: str = "") -> None:
        """Add frame ``frame``: gt_rgb / pred_rgb [C, H, W, 3], masks [C, H, W]."""
        tiles = {
            name: comparison_tiles(gt_rgb[c], object_mask[c], None if robot_mask is None else robot_mask[c],
                                   pred_rgb[c], self.error_max)
            for c, name in enumerate(camera_names)
        }
        row = _row(tiles, self.tile_width, labels=not self.rows)
        head = np.full((row.shape[0], 64, 3), 255, np.uint8)
        cv2.putText(head, f"f{frame}", (4, row.shape[0] // 2), _FONT, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
        if note:
            cv2.putText(head, note[:10], (4, row.shape[0] // 2 + 16), _FONT, 0.3, (60, 60, 60), 1, cv2.LINE_AA)
        self.rows.append((int(frame), np.concatenate([head, row], axis=1)))

    def write(self, path: str | Path) -> Optional[Path]:
        if not self.rows:
            return None
        rows = [r for _, r in sorted(self.rows, key=lambda x: x[0])]
        width = max(r.shape[1] for r in rows)
        rows = [np.pad(r, ((0, 2), (0, width - r.shape[1]), (0, 0)), constant_values=255) for r in rows]
        title = np.full((22, width, 3), 255, np.uint8)
        cv2.putText(title, self.title, (4, 15), _FONT, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
        img = np.concatenate([title, *rows], axis=0)
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        if not cv2.imwrite(str(path), img[..., ::-1]):
            raise RuntimeError(f"could not write contact sheet {path}")
        return path


class EpisodeVideo:
    """An mp4 of one episode, one frame per scored frame (all cameras side by side)."""

    def __init__(self, path: str | Path, fps: float = 10.0, tile_width: int = 240, error_max: float = 0.5) -> None:
        self.path = Path(path)
        self.fps = float(fps)
        self.tile_width = int(tile_width)
        self.error_max = float(error_max)
        self._writer: Optional[cv2.VideoWriter] = None
        self._size: Optional[tuple[int, int]] = None
        self.frames = 0

    def add(self, frame: int, camera_names: Sequence[str], gt_rgb: torch.Tensor, object_mask: torch.Tensor,
            robot_mask: Optional[torch.Tensor], pred_rgb: torch.Tensor) -> None:
        tiles = {
            name: comparison_tiles(gt_rgb[c], object_mask[c], None if robot_mask is None else robot_mask[c],
                                   pred_rgb[c], self.error_max)
            for c, name in enumerate(camera_names)
        }
        img = _row(tiles, self.tile_width, labels=True)
        cv2.putText(img, f"f{frame}", (img.shape[1] - 40, 10), _FONT, 0.33, (200, 0, 0), 1, cv2.LINE_AA)
        h, w = img.shape[:2]
        h2, w2 = h + (h % 2), w + (w % 2)  # codecs want even sizes
        img = np.pad(img, ((0, h2 - h), (0, w2 - w), (0, 0)), constant_values=255)
        if self._writer is None:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._writer = cv2.VideoWriter(str(self.path), cv2.VideoWriter_fourcc(*"mp4v"), self.fps, (w2, h2))
            if not self._writer.isOpened():
                self._writer = None
                raise RuntimeError(f"OpenCV cannot write mp4 video {self.path} (no mp4v encoder in this build)")
            self._size = (w2, h2)
        if (w2, h2) != self._size:
            raise ValueError("EpisodeVideo: frame size changed within an episode")
        self._writer.write(np.ascontiguousarray(img[..., ::-1]))
        self.frames += 1

    def close(self) -> Optional[Path]:
        if self._writer is None:
            return None
        self._writer.release()
        self._writer = None
        return self.path
