"""Bag ingestion settings: the ``data:`` section of a training config.

:class:`TopicNames` names the rig's topics (``{cam}`` = a camera's name, found from the topics
a bag has); :class:`DataConfig` says which episodes and cameras are read and how: masks a bag
lacks (:class:`~soma_ros.data.masks.MaskConfig`), synchronisation tolerance, resolution,
the deterministic train / test split of a folder without a manifest, and the validation
episodes.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Optional

from soma_ros.core.config import ConfigError
from soma_ros.data.bags import TopicConfig
from soma_ros.data.masks import MaskConfig

__all__ = ["TopicNames", "DataConfig"]


@dataclass
class TopicNames(TopicConfig):
    """Topic names of the rig (``{cam}`` = camera name): the fields of
    :class:`soma_ros.data.bags.TopicConfig`, validated as a config section."""

    def validate(self, where: str = "data.topics") -> None:
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            if not v:
                raise ConfigError(f"{where}.{f.name}: must not be empty")
        for f in ("color", "camera_info", "depth", "object_mask", "robot_mask"):
            if "{cam}" not in getattr(self, f):
                raise ConfigError(f"{where}.{f}: must contain '{{cam}}', got {getattr(self, f)!r}")


@dataclass
class DataConfig:
    """Bag ingestion and the train / validation episode lists.

    ``cameras``: camera names to use (None = every camera found in the bag).
    ``resolution_scale``: training images are the recorded ones resized by this
    factor (the paper trains dynamics at the recorded resolution: 1.0).
    ``max_frames``: use only the first frames of each episode (None = all).
    ``train_split`` / ``val_split``: manifest splits; ``val_split: null`` holds out
    the last ``val_holdout`` training episodes instead (never stepped on; the validation
    loss picks the kept checkpoint, ``run.keep``, so it must not be the test split when the
    test split is what the model is scored on). ``val_stratify`` (default): validation sees
    every task of the training split -- ``val_holdout`` is then the number held out *per task*
    (each task's last episodes; a task with a single training episode keeps it for training),
    and the validation list (of either kind) is ordered round-robin over the tasks, so that
    ``run.val_episodes`` keeps them balanced; off: the last ``val_holdout`` training episodes,
    whatever their task. ``tasks``: keep only
    episodes of these tasks (None = all). ``max_*_episodes`` cap the lists.
    ``require_masks``: a bag without object-mask topics is an error (else ``masks`` says
    where masks come from, derived from geometry by default: :mod:`soma_ros.data.masks`).
    ``strict``: a bad bag in a folder is fatal (else it is listed and skipped).
    ``split_test_fraction`` / ``split_seed``: the train / test split of a dataset without one
    (:func:`soma_ros.data.sources.default_split`).
    """

    cameras: Optional[list[str]] = None
    topics: TopicNames = field(default_factory=TopicNames)
    sync_tolerance_ms: float = 20.0
    require_masks: bool = False
    masks: MaskConfig = field(default_factory=MaskConfig)
    strict: bool = False
    split_test_fraction: float = 0.3
    split_seed: int = 0
    resolution_scale: float = 1.0
    max_frames: Optional[int] = None
    train_split: str = "train"
    val_split: Optional[str] = "test"
    val_holdout: int = 1
    val_stratify: bool = True
    tasks: Optional[list[str]] = None
    max_train_episodes: Optional[int] = None
    max_val_episodes: Optional[int] = None
    cache_episodes: int = 64

    def validate(self, where: str = "data") -> None:
        self.topics.validate(f"{where}.topics")
        self.masks.validate(f"{where}.masks")
        if not 0.0 <= self.split_test_fraction < 1.0:
            raise ConfigError(f"{where}.split_test_fraction: must lie in [0, 1), got {self.split_test_fraction}")
        if not (self.sync_tolerance_ms > 0 and math.isfinite(self.sync_tolerance_ms)):
            raise ConfigError(f"{where}.sync_tolerance_ms: must be > 0, got {self.sync_tolerance_ms}")
        if not (0.05 <= self.resolution_scale <= 4.0):
            raise ConfigError(f"{where}.resolution_scale: must lie in [0.05, 4], got {self.resolution_scale}")
        if self.max_frames is not None and self.max_frames < 2:
            raise ConfigError(f"{where}.max_frames: must be >= 2, got {self.max_frames}")
        if self.val_holdout < 0 or self.cache_episodes < 1:
            raise ConfigError(f"{where}: val_holdout >= 0 and cache_episodes >= 1 required")
