"""What `soma view` draws, on a viser server: the twin's layers in the browser.

Layers (each can be left out with ``layers=``):

* ``splats``  the Gaussian splats as splats (viser's WebGL Gaussian-splat renderer:
  centres, full 3x3 covariances, colours, opacities), optionally coloured by a
  per-splat error instead of their own colour;
* ``robot``   the robot's URDF visual meshes (read with trimesh), each link posed from a
  joint state as robot_state_publisher would (mimic joints follow their leader);
* ``cameras`` one frustum per camera at its optical-frame pose with its latest image,
  and a side panel per camera with the real image beside the simulated one when
  both exist;
* ``table``   the support plane ``n . x + d = 0`` as a translucent square around the
  object.

Everything is drawn in the simulation frame (the scene bundle's frame; ``world``
for the node), z against gravity as the bundle says. Arrays are numpy; shapes
are asserted where they enter.
"""

from __future__ import annotations

import threading
from pathlib import Path
from typing import Callable, Optional, Sequence

import numpy as np

__all__ = ["LAYERS", "TwinView", "default_view_pose", "error_colors", "matrix_to_wxyz_position", "splat_arrays"]

LAYERS = ("splats", "robot", "cameras", "table")


def matrix_to_wxyz_position(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """[4, 4] pose -> (quaternion w, x, y, z [4], position [3])."""
    import viser.transforms as vtf

    T = np.asarray(T, dtype=np.float64)
    assert T.shape == (4, 4), T.shape
    return vtf.SO3.from_matrix(T[:3, :3]).wxyz, T[:3, 3].copy()


def error_colors(err: np.ndarray, vmax: Optional[float] = None) -> np.ndarray:
    """Per-splat errors [N] (metres) -> RGB [N, 3] in [0, 1]: viridis from 0 to ``vmax``
    (default: the 95th percentile)."""
    from matplotlib import colormaps

    err = np.asarray(err, dtype=np.float64).reshape(-1)
    top = float(vmax) if vmax else float(np.percentile(err, 95)) if err.size else 1.0
    return colormaps["viridis"](np.clip(err / max(top, 1e-9), 0.0, 1.0))[:, :3]


def _image_u8(img: np.ndarray) -> np.ndarray:
    img = np.asarray(img)
    assert img.ndim == 3 and img.shape[2] == 3, img.shape
    if img.dtype != np.uint8:
        img = (np.clip(img, 0.0, 1.0) * 255).round().astype(np.uint8)
    return np.ascontiguousarray(img)


class TwinView:
    """The browser view of one twin: a viser server and its layers (module docstring).

    Thread-safe: sources update it from their own threads. ``port=0`` picks a free port
    (:attr:`port` says which)."""

    def __init__(self, host: str = "127.0.0.1", port: int = 8080, layers: Sequence[str] = LAYERS,
                 title: str = "soma view") -> None:
        import viser

        unknown = [x for x in layers if x not in LAYERS]
        if unknown:
            raise ValueError(f"unknown layer(s) {', '.join(unknown)} (known: {', '.join(LAYERS)})")
        self.layers = set(layers)
        if port == 0:
            import socket

            with socket.socket() as s:
                s.bind((host, 0))
                port = s.getsockname()[1]
        self.server = viser.ViserServer(host=host, port=port, label=title, verbose=False)
        self.port = int(self.server.get_port())
        self.host = host
        self.server.scene.set_up_direction("+z")
        self.server.scene.configure_fog(near=10.0, far=100.0, enabled=False)  # table-top distances: no haze
        self.server.scene.configure_default_lights(enabled=True, cast_shadow=False)
        self._lock = threading.Lock()
        self._splats = None
        self._splat_data: Optional[tuple] = None  # (means, covs, rgb, opacity) last drawn
        self._error: Optional[np.ndarray] = None
        self._robot = None
        self._bones: dict = {}  # parent link -> its bones' LineSegmentsHandle (a robot without meshes)
        self._posed: Optional[tuple] = None  # the (names, positions) the robot was last posed at
        self._robot_names: list[str] = []
        self._frustums: dict = {}
        self._panels: dict = {}
        self._fixed_view = False
        with self.server.gui.add_folder("Status"):
            self._status = self.server.gui.add_markdown("waiting for the twin ...")
        self.color_by_error = self.server.gui.add_checkbox("colour splats by error", False, disabled=True,
                                                            hint="per-splat error where the evaluation has it")
        self.color_by_error.on_update(lambda _: self._redraw_splats())

    @property
    def url(self) -> str:
        return f"http://{self.host}:{self.port}"

    # ------------------------------------------------------------------ layers
    def set_splats(self, means: np.ndarray, covs: np.ndarray, rgb: np.ndarray, opacity: np.ndarray,
                   error: Optional[np.ndarray] = None) -> None:
        """means [N, 3], covs [N, 3, 3], rgb [N, 3] in [0, 1], opacity [N] in [0, 1], error [N] (m) or None."""
        if "splats" not in self.layers:
            return
        n = means.shape[0]
        assert means.shape == (n, 3) and covs.shape == (n, 3, 3) and rgb.shape == (n, 3), \
            (means.shape, covs.shape, rgb.shape)
        opacity = np.asarray(opacity, dtype=np.float32).reshape(n, 1)
        with self._lock:
            self._splat_data = (np.asarray(means, np.float32), np.asarray(covs, np.float32),
                                np.asarray(rgb, np.float32), opacity)
            self._error = None if error is None else np.asarray(error, dtype=np.float64).reshape(n)
        if error is not None and self.color_by_error.disabled:
            self.color_by_error.disabled = False
        self._redraw_splats()

    def _redraw_splats(self) -> None:
        with self._lock:
            if self._splat_data is None:
                return
            means, covs, rgb, opacity = self._splat_data
            if self.color_by_error.value and self._error is not None:
                rgb = error_colors(self._error).astype(np.float32)
            # a new node of the same name replaces the old one in every client
            self._splats = self.server.scene.add_gaussian_splats("/splats", centers=means, covariances=covs,
                                                                 rgbs=rgb, opacities=opacity)

    def set_robot(self, urdf_path: Path, base_pose: np.ndarray) -> None:
        """Load the robot's visual meshes from `urdf_path`, its root link at `base_pose` [4, 4] in the
        view's frame; :meth:`set_joints` poses the links (by :class:`~soma_ros.core.robot_frames.RobotFrames`)."""
        if "robot" not in self.layers:
            return
        import trimesh

        from ..core.robot_frames import RobotFrames, rpy_matrix
        from ..core.robot_urdf import resolve_mesh_path

        urdf_path = Path(urdf_path)
        import xml.etree.ElementTree as ET

        root = ET.parse(urdf_path).getroot()
        self._frames = RobotFrames(urdf_path)
        self._base_pose = np.asarray(base_pose, dtype=np.float64)
        self._link_nodes = {}
        for link in root.iter("link"):
            name = link.get("name")
            meshes = []
            for vis in link.findall("visual"):
                geo = vis.find("geometry")
                mesh_el = None if geo is None else geo.find("mesh")
                if mesh_el is None:
                    continue
                origin = vis.find("origin")
                T = rpy_matrix([float(v) for v in (origin.get("xyz", "0 0 0") if origin is not None else "0 0 0").split()],
                               [float(v) for v in (origin.get("rpy", "0 0 0") if origin is not None else "0 0 0").split()])
                try:
                    m = trimesh.load(str(resolve_mesh_path(mesh_el.get("filename"), urdf_path.parent)), force="mesh")
                except (FileNotFoundError, ValueError) as exc:
                    print(f"soma view: robot link {name}: mesh not drawn ({exc})")
                    continue
                scale = [float(v) for v in mesh_el.get("scale", "1 1 1").split()]
                v = np.asarray(m.vertices, dtype=np.float64) * scale
                meshes.append((v @ T[:3, :3].T + T[:3, 3], np.asarray(m.faces, dtype=np.uint32)))
            if not meshes:
                continue
            node = self.server.scene.add_frame(f"/robot/{name}", show_axes=False)
            for k, (v, f) in enumerate(meshes):
                self.server.scene.add_mesh_simple(f"/robot/{name}/visual_{k}", vertices=v.astype(np.float32),
                                                  faces=f, color=(110, 115, 130), material="toon3")
            self._link_nodes[name] = node
        with_meshes = len(self._link_nodes)
        # a robot with no mesh to draw (none in the URDF, or the files missing): a bone from every
        # link's parent's origin to its own, in the parent's frame, so the kinematic chain shows
        bones: dict[str, list[np.ndarray]] = {}
        self._bones = {}
        if not with_meshes:
            for j in self._frames.urdf.joints.values():
                xyz = np.asarray(j.origin_xyz, dtype=np.float64)
                if np.linalg.norm(xyz) > 1e-4:
                    bones.setdefault(j.parent, []).append(xyz)
        for parent, ends in bones.items():
            node = self._link_nodes.get(parent) or self.server.scene.add_frame(f"/robot/{parent}", show_axes=False)
            pts = np.stack([np.stack([np.zeros(3), e]) for e in ends]).astype(np.float32)  # [S, 2, 3]
            self._bones[parent] = self.server.scene.add_line_segments(
                f"/robot/{parent}/bones", points=pts, colors=(110, 115, 130), thickness=0.02)
            self._link_nodes[parent] = node
        self._robot = self._frames
        self._robot_names = []
        self._posed = None
        self.set_joints([], [])
        print(f"soma view: robot drawn ({with_meshes} links with meshes, {sum(map(len, bones.values()))} bones "
              "for links without)", flush=True)

    def set_joints(self, names: Sequence[str], positions: Sequence[float]) -> None:
        """Pose the robot's links from a joint state (names [J], positions [J]); joints it does not
        name are held at 0 clamped into their limits."""
        if self._robot is None:
            return
        key = (tuple(names), tuple(float(v) for v in positions))
        if key == self._posed:  # unchanged: nothing to send
            return
        self._posed = key
        poses = self._frames.link_poses(list(names), np.asarray(list(positions), dtype=np.float64))
        for name, node in self._link_nodes.items():
            wxyz, pos = matrix_to_wxyz_position(self._base_pose @ poses[name][0])
            node.wxyz, node.position = wxyz, pos

    def set_camera(self, name: str, K: np.ndarray, width: int, height: int, cam_to_view: np.ndarray,
                   sim_image: Optional[np.ndarray] = None, real_image: Optional[np.ndarray] = None,
                   scale: float = 0.08) -> None:
        """Camera `name` with intrinsics K [3, 3] at optical-frame pose cam_to_view [4, 4] (x right,
        y down, z forward, as viser's frustums): the frustum shows the simulated image (else the real
        one), the side panel shows real | simulated."""
        if "cameras" not in self.layers:
            return
        K = np.asarray(K, dtype=np.float64).reshape(3, 3)
        fov = 2.0 * np.arctan2(height / 2.0, K[1, 1])
        wxyz, pos = matrix_to_wxyz_position(cam_to_view)
        shown = sim_image if sim_image is not None else real_image
        img = None if shown is None else _image_u8(shown)
        shape = (float(fov), float(width) / float(height), float(scale), img is None)
        old = self._frustums.get(name)
        if old is not None and old[1] == shape:  # the same frustum: new image and pose only
            old[0].wxyz, old[0].position = wxyz, pos
            if img is not None:
                old[0].image = img
        else:
            self._frustums[name] = (self.server.scene.add_camera_frustum(
                f"/cameras/{name}", fov=shape[0], aspect=shape[1], scale=scale, image=img,
                wxyz=wxyz, position=pos, color=(40, 120, 220)), shape)
        tiles = [_image_u8(x) for x in (real_image, sim_image) if x is not None]
        if not tiles:
            return
        h = min(t.shape[0] for t in tiles)
        tiles = [t[:h] for t in tiles]
        panel = np.concatenate(tiles, axis=1)
        if name not in self._panels:
            label = "real | simulated" if len(tiles) == 2 else ("simulated" if sim_image is not None else "real")
            with self.server.gui.add_folder(f"{name}: {label}"):
                self._panels[name] = self.server.gui.add_image(panel, format="jpeg")
        else:
            self._panels[name].image = panel

    def set_table(self, normal: np.ndarray, offset: float, center: np.ndarray, size: float = 1.0) -> None:
        """The plane ``normal . x + offset = 0`` as a square of side `size` m around `center` [3]."""
        if "table" not in self.layers:
            return
        n = np.asarray(normal, dtype=np.float64).reshape(3)
        n = n / np.linalg.norm(n)
        c = np.asarray(center, dtype=np.float64).reshape(3)
        c = c - (n @ c + float(offset)) * n  # onto the plane
        a = np.cross(n, [1.0, 0.0, 0.0] if abs(n[0]) < 0.9 else [0.0, 1.0, 0.0])
        a /= np.linalg.norm(a)
        b = np.cross(n, a)
        h = size / 2.0
        verts = np.stack([c + h * (sa * a + sb * b) for sa, sb in ((-1, -1), (1, -1), (1, 1), (-1, 1))])
        faces = np.array([[0, 1, 2], [0, 2, 3], [0, 2, 1], [0, 3, 2]], dtype=np.uint32)  # both sides
        self.server.scene.add_mesh_simple("/table", vertices=verts.astype(np.float32), faces=faces,
                                          color=(120, 100, 80), material="toon3", side="double")

    def set_status(self, lines: dict) -> None:
        """Live status: {label: value} shown as a small table."""
        rows = "\n".join(f"| {k} | {v} |" for k, v in lines.items())
        self._status.content = "| | |\n|---|---|\n" + rows

    def look_at(self, target: np.ndarray, position: np.ndarray) -> None:
        """Where a newly connected browser's camera starts (and every connected one now)."""
        target = np.asarray(target, dtype=np.float64)
        position = np.asarray(position, dtype=np.float64)
        self.server.initial_camera.look_at = target
        self.server.initial_camera.position = position
        for client in self.server.get_clients().values():
            client.camera.position = position
            client.camera.look_at = target

    def on_connect(self, fn: Callable) -> None:
        self.server.on_client_connect(fn)

    def close(self) -> None:
        self.server.stop()


def default_view_pose(center: np.ndarray, robot_base: Optional[np.ndarray], up: np.ndarray,
                      radius: float = 0.15) -> tuple[np.ndarray, np.ndarray]:
    """(target, eye) for the browser camera: looking at the object (centre, radius m) from the
    side away from the robot base (so both the object and the robot are in view), raised along
    `up`, from 4 radii away (0.4 to 3 m)."""
    distance = float(np.clip(4.0 * radius, 0.4, 3.0))
    center = np.asarray(center, dtype=np.float64)
    up = np.asarray(up, dtype=np.float64) / np.linalg.norm(up)
    away = np.array([1.0, 0.0, 0.0]) if robot_base is None else center - np.asarray(robot_base, dtype=np.float64)
    away = away - (away @ up) * up
    if np.linalg.norm(away) < 1e-6:
        away = np.cross(up, [0.0, 1.0, 0.0]) if abs(up[1]) < 0.9 else np.cross(up, [1.0, 0.0, 0.0])
    away /= np.linalg.norm(away)
    side = np.cross(up, away)
    eye = center + distance * (0.75 * away + 0.35 * side + 0.55 * up)
    return center, eye


def splat_arrays(splats, T_view_frame: Optional[np.ndarray] = None) -> tuple[np.ndarray, ...]:
    """Splats (in a frame F) -> (means [N, 3], covs [N, 3, 3], rgb [N, 3], opacity [N]) in the view's
    frame, with ``T_view_frame`` [4, 4] the rigid pose of F (None: identity)."""
    means = splats.means.detach().double().cpu().numpy()
    covs = splats.covariances().detach().double().cpu().numpy()
    if T_view_frame is not None and not np.allclose(T_view_frame, np.eye(4)):
        R, t = T_view_frame[:3, :3], T_view_frame[:3, 3]
        means = means @ R.T + t
        covs = R[None] @ covs @ R.T[None]
    rgb = splats.colors().detach().double().cpu().numpy()
    return (means.astype(np.float32), covs.astype(np.float32), rgb.astype(np.float32),
            splats.opacities.detach().double().cpu().numpy().astype(np.float32))
