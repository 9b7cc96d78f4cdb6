"""`soma view --resim OUT`: play a `soma resim` output back with a time slider.

Reads ``OUT/resim_bag`` (the recorded bag with the simulated topics beside it) with
rosbags, no ROS needed. One frame per ``<p>/splats`` message; for the frame at stamp t
the view shows:

* the simulated splats; with ``/world/object_points`` (the reference world's ground
  truth, as the evaluation uses it) each splat can be coloured by its distance to the
  nearest ground-truth point (the "colour splats by error" box; metres, viridis,
  0 to the 95th percentile);
* the robot's meshes from the bag's /robot_description, posed by the newest
  /joint_states at or before t, its base from /tf_static;
* each camera's frustum at its pose from TF (the simulated camera frames), with the
  recorded colour image beside the simulated one in its panel;
* the table plane of the scene bundle given as ``--scene`` (the run's ``scene/``; none
  without it: the bag does not record the table).

Messages are indexed once and decoded when a frame is shown, so a long bag does not
have to fit in memory as decoded messages.
"""

from __future__ import annotations

import bisect
import tempfile
import threading
from pathlib import Path
from typing import Optional

import numpy as np

from .scene import TwinView, default_view_pose, splat_arrays
from .tf_graph import TfGraph

__all__ = ["ResimSource", "find_resim_bag"]


def find_resim_bag(out: str) -> Path:
    p = Path(out)
    bag = p / "resim_bag" if (p / "resim_bag").is_dir() else p
    if not (bag / "metadata.yaml").is_file():
        raise FileNotFoundError(f"no rosbag2 at {bag} (give a `soma resim` output directory, which holds resim_bag/)")
    return bag


def _rgb(msg) -> Optional[np.ndarray]:
    enc = msg.encoding.lower()
    if enc not in ("rgb8", "bgr8"):
        return None
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    img = np.asarray(msg.data, np.uint8)[: step * h].reshape(h, step)[:, : 3 * w].reshape(h, w, 3)
    return np.ascontiguousarray(img[..., ::-1] if enc == "bgr8" else img)


class ResimSource:
    def __init__(self, view: TwinView, out: str, scene: Optional[str] = None, prefix: str = "/soma",
                 world_frame: str = "world") -> None:
        from rosbags.highlevel import AnyReader

        from ..bagtypes import typestore

        self.view, self.prefix, self.world = view, prefix.rstrip("/"), world_frame
        self.bag = find_resim_bag(out)
        self.scene = scene
        self._reader = AnyReader([self.bag], default_typestore=typestore())
        self._reader.open()
        self._index: dict[str, list[tuple[int, object, int]]] = {}  # topic -> [(stamp, conn, position)]
        self._raw: dict[tuple[str, int], bytes] = {}
        from tqdm import tqdm

        conns = list(self._reader.connections)
        for conn, ts, raw in tqdm(self._reader.messages(connections=conns), desc="indexing the resim bag",
                                  unit="msg", leave=False):
            lst = self._index.setdefault(conn.topic, [])
            self._raw[(conn.topic, len(lst))] = raw
            lst.append((ts, conn, len(lst)))
        splat_topic = f"{self.prefix}/splats"
        if splat_topic not in self._index:
            raise ValueError(f"{self.bag}: no {splat_topic} (is this a `soma resim` output?)")
        self.frames = [ts for ts, _, _ in self._index[splat_topic]]
        self.cams = sorted({t.split("/")[-2] for t in self._index
                            if t.startswith(self.prefix + "/") and t.endswith("/image_raw")})
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._shown: Optional[int] = None
        self._robot = False
        self._controls()
        self._setup_static()

    # ------------------------------------------------------------------ bag access
    def _decode(self, topic: str, i: int):
        ts, conn, pos = self._index[topic][i]
        return self._reader.deserialize(self._raw[(topic, pos)], conn.msgtype)

    def _at(self, topic: str, stamp: int):
        """The newest message of `topic` at or before `stamp` (None if none)."""
        lst = self._index.get(topic)
        if not lst:
            return None
        i = bisect.bisect_right([ts for ts, _, _ in lst], stamp) - 1
        return None if i < 0 else self._decode(topic, i)

    def _tf_at(self, stamp: int) -> TfGraph:
        g = TfGraph()
        for k in range(len(self._index.get("/tf_static", []))):
            g.add(self._decode("/tf_static", k))
        for k, (ts, _, _) in enumerate(self._index.get("/tf", [])):
            if ts > stamp:
                break
            g.add(self._decode("/tf", k))
        return g

    # ------------------------------------------------------------------ setup
    def _controls(self) -> None:
        gui = self.view.server.gui
        with gui.add_folder("Playback"):
            self.slider = gui.add_slider("frame", min=0, max=max(len(self.frames) - 1, 0), step=1, initial_value=0)
            self.play = gui.add_checkbox("play", False)
            self.fps = gui.add_slider("frames per second", min=0.5, max=30.0, step=0.5, initial_value=5.0)
        self.slider.on_update(lambda _: self.show(int(self.slider.value)))

    def _setup_static(self) -> None:
        g = self._tf_at(self.frames[0])
        desc = self._at("/robot_description", self.frames[-1])
        if desc is not None:
            import xml.etree.ElementTree as ET

            root = ET.fromstring(desc.data)
            children = {j.find("child").get("link") for j in root.iter("joint") if j.find("child") is not None}
            base = next((lk.get("name") for lk in root.iter("link") if lk.get("name") not in children), None)
            T = g.lookup(base, self.world) if base else None
            if T is not None:
                f = Path(tempfile.mkdtemp(prefix="soma_view_")) / "robot_description.urdf"
                f.write_text(desc.data)
                self.view.set_robot(f, T)
                self._robot = True
        self._base = None if not self._robot else T[:3, 3]
        self._table()

    def _table(self) -> None:
        if self.scene is None:
            return
        from ..core.scene_bundle import SceneBundle

        bundle = SceneBundle.load(self.scene)
        self._table_plane = (np.asarray(bundle.table_normal, float), float(bundle.table_offset))

    # ------------------------------------------------------------------ frames
    def show(self, i: int) -> None:
        from scipy.spatial import cKDTree

        from ..core.cloud_layout import cloud_to_splats, points_from_cloud

        i = int(np.clip(i, 0, len(self.frames) - 1))
        stamp = self.frames[i]
        g = self._tf_at(stamp)
        cloud = self._decode(f"{self.prefix}/splats", i)
        splats = cloud_to_splats(cloud)
        T = g.lookup(cloud.header.frame_id, self.world)
        means, covs, rgb, opacity = splat_arrays(splats, T)
        err = None
        gt = self._at("/world/object_points", stamp)
        if gt is not None:
            pts = points_from_cloud(gt).astype(np.float64)
            Tg = g.lookup(gt.header.frame_id, self.world)
            if Tg is not None and len(pts):
                pts = pts @ Tg[:3, :3].T + Tg[:3, 3]
                err, _ = cKDTree(pts).query(means.astype(np.float64))
        self.view.set_splats(means, covs, rgb, opacity, error=err)
        if self._shown is None:
            if hasattr(self, "_table_plane"):
                self.view.set_table(*self._table_plane, means.mean(0))
            target, eye = default_view_pose(means.mean(0), self._base, np.array([0.0, 0.0, 1.0]),
                                            radius=float(np.linalg.norm(means - means.mean(0), axis=1).max()))
            self.view.look_at(target, eye)
        js = self._at("/joint_states", stamp)
        if js is not None:
            self.view.set_joints(list(js.name), list(np.asarray(js.position)))
        for cam in self.cams:
            sim = self._at(f"{self.prefix}/{cam}/image_raw", stamp)
            info = self._at(f"{self.prefix}/{cam}/camera_info", stamp)
            if sim is None or info is None:
                continue
            Tc = g.lookup(info.header.frame_id, self.world)
            if Tc is None:
                continue
            real = self._at(f"/{cam}/color/image_raw", stamp)
            self.view.set_camera(cam, np.asarray(info.k).reshape(3, 3), int(info.width), int(info.height), Tc,
                                 sim_image=_rgb(sim), real_image=None if real is None else _rgb(real))
        status = {"mode": f"resim ({self.bag.parent.name})", "frame": f"{i + 1} / {len(self.frames)}",
                  "time (s)": f"{(stamp - self.frames[0]) / 1e9:.2f}", "splats": len(means)}
        if err is not None:
            status["error to ground truth (mm)"] = f"mean {1e3 * float(np.mean(err)):.1f}, max {1e3 * float(np.max(err)):.1f}"
        self.view.set_status(status)
        self._shown = i

    def start(self) -> None:
        self.show(0)

        def loop() -> None:
            while not self._stop.is_set():
                if self.play.value and len(self.frames) > 1:
                    nxt = (int(self.slider.value) + 1) % len(self.frames)
                    self.slider.value = nxt  # on_update shows it
                self._stop.wait(1.0 / float(self.fps.value))

        t = threading.Thread(target=loop, name="soma_view_play", daemon=True)
        t.start()
        self._threads.append(t)

    def stop(self) -> None:
        self._stop.set()
        for t in self._threads:
            t.join(timeout=5.0)
        self._reader.close()
