"""The scene bundle: everything a node or a rollout needs besides the model.

A scene bundle is a directory::

    scene/
      splats.ply     initial splats G_0 (standard 3DGS .ply), simulation frame
      scene.json     frame names, gravity, table plane, dt, the robot and its
                     robot->simulation similarity, the cameras

``scene.json``::

    {"version": 2,
     "sim_frame": "world",             # frame of splats and cameras
     "object": "rope",                 # object config name (hierarchy thresholds)
     "dt": 0.0333,                     # s, the frame interval the model was trained at
     "gravity": [gx, gy, gz],          # m/s^2, simulation frame
     "table": {"normal": [3], "offset": d},   # n.x + d = 0, n against gravity
     "robot": {"config": "panda" | path, "base_to_sim": Sim3 dict},
     "cameras": [{"name", "width", "height", "K": [[3x3]],         # pixel centres at +0.5 (below)
                  "cam_to_sim": [[4x4]]                      # fixed camera, or
                  | "mount": {"link": L, "link_to_cam": [[4x4]]}}]}   # on a robot link

All units are SI (metres, seconds); poses are OpenCV optical frames for cameras.

``K`` follows the renderer's convention: pixel (u, v) covers [u, u + 1) x [v, v + 1), so its
centre is at u + 0.5 (as in 3DGS), whereas a ROS ``CameraInfo`` puts pixel centres at integers
(:func:`soma_ros.core.cameras.k_from_camera_info` converts). Version 1 bundles set up from a bag
stored the CameraInfo ``K`` unconverted, half a pixel off; they are refused with a one-line
message (set the scene up again). Version 1 bundles from a capture folder or a splat file
(``soma reconstruct --capture``, ``soma scene align --capture``) already used the renderer's
convention and load as they are.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Optional

import numpy as np

from .splats import Splats

VERSION = 2


@dataclass
class CameraSpec:
    name: str
    width: int
    height: int
    K: np.ndarray  # [3, 3]
    cam_to_sim: Optional[np.ndarray] = None  # [4, 4] for a fixed camera
    mount_link: Optional[str] = None  # robot link for a mounted camera
    link_to_cam: Optional[np.ndarray] = None  # [4, 4]

    def __post_init__(self) -> None:
        self.K = np.asarray(self.K, dtype=np.float64).reshape(3, 3)
        if (self.cam_to_sim is None) == (self.mount_link is None):
            raise ValueError(f"camera '{self.name}': give exactly one of cam_to_sim or a mount link")
        if self.cam_to_sim is not None:
            self.cam_to_sim = np.asarray(self.cam_to_sim, dtype=np.float64).reshape(4, 4)
        if self.mount_link is not None:
            if self.link_to_cam is None:
                raise ValueError(f"camera '{self.name}': a mounted camera needs link_to_cam")
            self.link_to_cam = np.asarray(self.link_to_cam, dtype=np.float64).reshape(4, 4)

    def to_json(self) -> dict:
        d: dict[str, Any] = {"name": self.name, "width": int(self.width), "height": int(self.height), "K": self.K.tolist()}
        if self.cam_to_sim is not None:
            d["cam_to_sim"] = self.cam_to_sim.tolist()
        else:
            d["mount"] = {"link": self.mount_link, "link_to_cam": self.link_to_cam.tolist()}
        return d

    @staticmethod
    def from_json(d: dict) -> "CameraSpec":
        mount = d.get("mount")
        return CameraSpec(name=d["name"], width=int(d["width"]), height=int(d["height"]), K=np.asarray(d["K"]),
                          cam_to_sim=None if mount else np.asarray(d["cam_to_sim"]),
                          mount_link=mount["link"] if mount else None,
                          link_to_cam=np.asarray(mount["link_to_cam"]) if mount else None)


@dataclass
class SceneBundle:
    splats: Splats
    gravity: np.ndarray  # [3]
    table_normal: np.ndarray  # [3]
    table_offset: float
    dt: float
    sim_frame: str = "world"
    object_name: str = "rope"
    robot_config: str = "panda"
    base_to_sim: dict = field(default_factory=lambda: {"scale": 1.0, "rotation": np.eye(3).tolist(), "translation": [0.0, 0.0, 0.0]})
    cameras: list[CameraSpec] = field(default_factory=list)
    extra: dict = field(default_factory=dict)

    def scene_context(self):
        """The simulator's SceneContext for this bundle."""
        import torch

        from .simulator import SceneContext

        return SceneContext(torch.tensor(self.gravity, dtype=torch.float32),
                            torch.tensor(self.table_normal, dtype=torch.float32), float(self.table_offset), float(self.dt))

    def base_to_sim_sim3(self):
        from .calibration import Sim3

        return Sim3.from_dict(self.base_to_sim)

    def save(self, folder: str | Path) -> Path:
        from .ply import write_ply

        folder = Path(folder)
        folder.mkdir(parents=True, exist_ok=True)
        write_ply(folder / "splats.ply", self.splats)
        meta = {
            "version": VERSION, "sim_frame": self.sim_frame, "object": self.object_name, "dt": float(self.dt),
            "gravity": np.asarray(self.gravity, dtype=float).tolist(),
            "table": {"normal": np.asarray(self.table_normal, dtype=float).tolist(), "offset": float(self.table_offset)},
            "robot": {"config": self.robot_config, "base_to_sim": _jsonable(self.base_to_sim)},
            "cameras": [c.to_json() for c in self.cameras], "extra": _jsonable(self.extra),
        }
        tmp = folder / "scene.json.tmp"
        tmp.write_text(json.dumps(meta, indent=2))
        tmp.replace(folder / "scene.json")
        return folder

    @staticmethod
    def load(folder: str | Path) -> "SceneBundle":
        from .ply import load_splats

        folder = Path(folder)
        meta_path = folder / "scene.json"
        if not meta_path.is_file():
            raise FileNotFoundError(f"scene bundle {folder} has no scene.json")
        meta = json.loads(meta_path.read_text())
        _check_version(folder, meta)
        try:
            return SceneBundle(
                splats=load_splats(folder / "splats.ply"), gravity=np.asarray(meta["gravity"], dtype=np.float64),
                table_normal=np.asarray(meta["table"]["normal"], dtype=np.float64),
                table_offset=float(meta["table"]["offset"]), dt=float(meta["dt"]), sim_frame=meta["sim_frame"],
                object_name=meta.get("object", "rope"), robot_config=meta["robot"]["config"],
                base_to_sim=meta["robot"]["base_to_sim"],
                cameras=[CameraSpec.from_json(c) for c in meta.get("cameras", [])], extra=meta.get("extra", {}),
            )
        except KeyError as exc:
            raise ValueError(f"scene bundle {folder}: scene.json lacks {exc}") from None


def _check_version(folder: Path, meta: dict) -> None:
    """Refuse a scene.json this version cannot read correctly (see the module docstring)."""
    version = meta.get("version")
    if version == VERSION:
        return
    if version == 1:
        if "source_bag" not in (meta.get("extra") or {}):
            return  # capture or splat-file cameras: K was already in the renderer's convention
        raise ValueError(f"scene bundle {folder} is version 1, set up from a bag with its CameraInfo K half a "
                         f"pixel off; set it up again (soma train into a new --out, or soma reconstruct --bag)")
    raise ValueError(f"scene bundle {folder}: version {version} is not {VERSION}")


def _jsonable(x):
    if isinstance(x, dict):
        return {k: _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return x.tolist()
    if hasattr(x, "tolist"):
        return x.tolist()
    return x
