"""A scene folder on disk: the scene bundle, its hierarchy and how it was set up.

``save_scene`` writes the bundle (:class:`~soma_ros.core.scene_bundle.SceneBundle`: splats,
table plane, gravity, robot -> sim transform, cameras), ``hierarchy.pt`` and, when given,
``setup.json``; ``load_scene`` reads them back. Training, evaluation, resimulation and the
node all start from such a folder (``RUN/scene``).
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Optional

import torch

from soma_ros.core.checkpoint import atomic_torch_save
from soma_ros.core.config import load_object_config
from soma_ros.core.hierarchy import Hierarchy, build_hierarchy
from soma_ros.core.scene_bundle import SceneBundle

__all__ = ["save_scene", "load_scene"]


def _atomic_write_text(path: Path, text: str) -> None:
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(text)
    os.replace(tmp, path)


def save_scene(folder: Path, bundle: SceneBundle, hierarchy: Hierarchy, info: Optional[dict] = None) -> Path:
    """Scene bundle + ``hierarchy.pt`` (+ ``setup.json``) in ``folder``."""
    folder = Path(folder)
    bundle.save(folder)
    atomic_torch_save(hierarchy.to_dict(), folder / "hierarchy.pt")
    if info is not None:
        _atomic_write_text(folder / "setup.json", json.dumps(info, indent=1, default=float))
    return folder


def load_scene(folder: Path) -> tuple[SceneBundle, Hierarchy]:
    """(bundle, hierarchy) from a folder written by :func:`save_scene` (the hierarchy is rebuilt
    from the splats when ``hierarchy.pt`` is absent, e.g. a hand-made bundle)."""
    folder = Path(folder)
    bundle = SceneBundle.load(folder)
    hp = folder / "hierarchy.pt"
    if hp.is_file():
        hier = Hierarchy.from_dict(torch.load(hp, weights_only=True))
        if hier.sizes[0] != len(bundle.splats):
            raise ValueError(f"{hp}: hierarchy is for {hier.sizes[0]} splats, the bundle has {len(bundle.splats)}")
    else:
        oc = load_object_config(bundle.object_name)
        hier = build_hierarchy(bundle.splats.means.float(), bundle.splats.mass.float(), oc.hierarchy.thresholds,
                               oc.hierarchy.seed_fraction)
    return bundle, hier
