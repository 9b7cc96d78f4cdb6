"""Read a recorded episode (rosbag2, sqlite3 or mcap) into synchronised arrays.

Topic conventions are those of a real RealSense rig (remappable through
:class:`TopicConfig`):

  /joint_states                                sensor_msgs/JointState
  /<cam>/color/image_raw                       sensor_msgs/Image rgb8 (bgr8 accepted)
  /<cam>/color/camera_info                     sensor_msgs/CameraInfo
  /<cam>/aligned_depth_to_color/image_raw      sensor_msgs/Image 16UC1 (mm) or 32FC1 (m)
  /<cam>/object_mask, /<cam>/robot_mask        sensor_msgs/Image mono8 (optional)
  /tf_static                                   tf2_msgs/TFMessage

Frames are synchronised on the colour image stamps of the first camera; every
other stream is matched to the nearest stamp within a tolerance, joint states
are interpolated linearly by stamp (their efforts too, when every message has one
per joint: :attr:`Episode.joint_efforts`). The evaluation-only ground-truth topic
``/world/object_points`` is never deserialised here (see
:data:`FORBIDDEN_TOPICS`); training code reads bags only through this module.

Errors are one line and name the problem: a missing topic, a wrong encoding,
an empty /joint_states, a frame absent from /tf_static.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Optional, Sequence

import numpy as np

#: topics that training code must never read (evaluation-only ground truth)
FORBIDDEN_TOPICS = ("/world/object_points",)


class BagError(ValueError):
    """A bag that cannot be used for training, with a one-line reason."""


@dataclass
class TopicConfig:
    """Topic names of a rig; `{cam}` is replaced by each camera name."""

    joint_states: str = "/joint_states"
    color: str = "/{cam}/color/image_raw"
    camera_info: str = "/{cam}/color/camera_info"
    depth: str = "/{cam}/aligned_depth_to_color/image_raw"
    object_mask: str = "/{cam}/object_mask"
    robot_mask: str = "/{cam}/robot_mask"
    tf_static: str = "/tf_static"
    world_frame: str = "world"

    def topic(self, kind: str, cam: str) -> str:
        return getattr(self, kind).format(cam=cam)


@dataclass
class CameraStream:
    """One camera over an episode. T frames of H x W."""

    name: str
    frame_id: str
    K: np.ndarray  # [3, 3] float64, pixels
    width: int
    height: int
    rgb: np.ndarray  # [T, H, W, 3] uint8
    depth: Optional[np.ndarray]  # [T, H, W] float32 metres, 0 = invalid
    object_mask: Optional[np.ndarray]  # [T, H, W] bool
    robot_mask: Optional[np.ndarray]  # [T, H, W] bool
    cam_to_world: Optional[np.ndarray] = None  # [T, 4, 4] float64 (filled by resolve_camera_poses)


@dataclass
class Episode:
    """A synchronised episode: T frames, J joints, cameras by name."""

    path: Path
    stamps_ns: np.ndarray  # [T] int64, the frame clock (first camera's colour stamps)
    joint_names: list[str]
    joint_positions: np.ndarray  # [T, J] float64, interpolated at stamps_ns
    cameras: dict[str, CameraStream]
    static_tf: dict[tuple[str, str], np.ndarray] = field(default_factory=dict)  # (parent, child) -> [4,4]
    #: [T, J] float64 (N m / N), interpolated at stamps_ns; None when /joint_states carries no efforts
    joint_efforts: Optional[np.ndarray] = None

    @property
    def num_frames(self) -> int:
        return int(self.stamps_ns.shape[0])

    def joint_state_at(self, t: int) -> tuple[list[str], np.ndarray]:
        return self.joint_names, self.joint_positions[t]


# ---------------------------------------------------------------- decoding
def decode_image(msg, topic: str, allowed: Sequence[str]) -> np.ndarray:
    """sensor_msgs/Image -> numpy ([H,W,3] uint8 rgb, [H,W] uint16/float32, [H,W] uint8)."""
    enc = msg.encoding.lower()
    if enc not in allowed:
        raise BagError(f"{topic}: image encoding '{msg.encoding}' is not one of {', '.join(allowed)}")
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    buf = np.asarray(msg.data, dtype=np.uint8)
    chans, dtype = {"rgb8": (3, np.uint8), "bgr8": (3, np.uint8), "mono8": (1, np.uint8),
                    "8uc1": (1, np.uint8), "16uc1": (1, np.uint16), "mono16": (1, np.uint16),
                    "32fc1": (1, np.float32)}[enc]
    row_bytes = w * chans * np.dtype(dtype).itemsize
    if step < row_bytes or buf.size < step * h:
        raise BagError(f"{topic}: image buffer too small ({buf.size} bytes for {h}x{w} {enc}, step {step})")
    rows = buf[: step * h].reshape(h, step)[:, :row_bytes]
    arr = np.ascontiguousarray(rows).view(dtype)
    if int(getattr(msg, "is_bigendian", 0)) and np.dtype(dtype).itemsize > 1:
        arr = arr.byteswap()
    arr = arr.reshape(h, w, chans) if chans > 1 else arr.reshape(h, w)
    if enc == "bgr8":
        arr = arr[..., ::-1]
    return np.ascontiguousarray(arr)


def tf_to_matrix(tr) -> np.ndarray:
    """geometry_msgs/Transform -> [4, 4] float64."""
    q = tr.rotation
    w, x, y, z = float(q.w), float(q.x), float(q.y), float(q.z)
    n = np.sqrt(w * w + x * x + y * y + z * z)
    if not np.isfinite(n) or n < 1e-9:
        raise BagError("a /tf_static transform has an invalid quaternion")
    w, x, y, z = w / n, x / n, y / n, z / n
    R = np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = [tr.translation.x, tr.translation.y, tr.translation.z]
    return T


def _stamp_ns(header) -> int:
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


def _nearest(src_ns: np.ndarray, query_ns: np.ndarray, tol_ns: int, topic: str) -> np.ndarray:
    idx = np.clip(np.searchsorted(src_ns, query_ns), 1, max(len(src_ns) - 1, 1))
    lo = np.clip(idx - 1, 0, len(src_ns) - 1)
    hi = np.clip(idx, 0, len(src_ns) - 1)
    pick = np.where(np.abs(src_ns[lo] - query_ns) <= np.abs(src_ns[hi] - query_ns), lo, hi)
    err = np.abs(src_ns[pick] - query_ns)
    if (err > tol_ns).any():
        worst = int(err.max()) / 1e6
        raise BagError(f"{topic}: no message within {tol_ns / 1e6:.1f} ms of a frame (worst {worst:.1f} ms)")
    return pick


# ------------------------------------------------------------------ reading
def list_topics(bag: Path) -> dict[str, str]:
    from rosbags.highlevel import AnyReader

    from soma_ros.bagtypes import typestore

    with AnyReader([Path(bag)], default_typestore=typestore()) as r:
        return {c.topic: c.msgtype for c in r.connections}


def read_episode(
    bag: str | Path,
    cameras: Optional[Sequence[str]] = None,
    topics: Optional[TopicConfig] = None,
    sync_tolerance_ms: float = 20.0,
    require_masks: bool = True,
    max_frames: Optional[int] = None,
) -> Episode:
    """Read one episode bag. `cameras=None` discovers every camera with colour + info topics."""
    from rosbags.highlevel import AnyReader

    from soma_ros.bagtypes import typestore

    topics = topics or TopicConfig()
    bag = Path(bag)
    if not bag.exists():
        raise BagError(f"bag not found: {bag}")
    with AnyReader([bag], default_typestore=typestore()) as reader:
        by_topic = {c.topic: c for c in reader.connections}
        if cameras is None:
            # a camera is any name with a colour, camera-info or depth topic; all three are then required
            found = set()
            for kind in ("color", "camera_info", "depth"):
                pattern = getattr(topics, kind)
                prefix, suffix = pattern.split("{cam}")[0], pattern.split("{cam}")[-1]
                found |= {t[len(prefix): len(t) - len(suffix)] for t in by_topic
                          if t.startswith(prefix) and t.endswith(suffix) and len(t) > len(prefix) + len(suffix)
                          and t not in FORBIDDEN_TOPICS}
            cameras = sorted(found)
            if not cameras:
                raise BagError(f"{bag.name}: no camera topics matching {topics.color}")
        needed = [topics.joint_states, topics.tf_static]
        for cam in cameras:
            needed += [topics.topic("color", cam), topics.topic("camera_info", cam), topics.topic("depth", cam)]
            if require_masks:
                needed += [topics.topic("object_mask", cam)]
        missing = [t for t in needed if t not in by_topic]
        if missing:
            raise BagError(f"{bag.name}: missing topic {missing[0]}" + (f" (+{len(missing) - 1} more)" if len(missing) > 1 else ""))
        wanted = set(needed)
        for cam in cameras:
            for kind in ("object_mask", "robot_mask"):
                if topics.topic(kind, cam) in by_topic:
                    wanted.add(topics.topic(kind, cam))
        wanted -= set(FORBIDDEN_TOPICS)
        conns = [by_topic[t] for t in wanted]

        raw: dict[str, list] = {t: [] for t in wanted}
        for conn, _t, data in reader.messages(connections=conns):
            msg = reader.deserialize(data, conn.msgtype)
            raw[conn.topic].append(msg)

    # ---- joint states
    js = raw[topics.joint_states]
    if not js:
        raise BagError(f"{bag.name}: {topics.joint_states} is empty")
    names = list(js[0].name)
    if not names:
        raise BagError(f"{bag.name}: {topics.joint_states} has no joint names")
    js_ns, js_pos, js_eff = [], [], []
    for m in js:
        idx = {n: i for i, n in enumerate(m.name)}
        if any(n not in idx for n in names):
            continue
        pos = np.array([m.position[idx[n]] for n in names], dtype=np.float64) if len(m.position) == len(m.name) else None
        if pos is None or not np.all(np.isfinite(pos)):
            continue
        # efforts only where the message has one per name (JointState allows an empty array)
        eff = np.array([m.effort[idx[n]] for n in names], dtype=np.float64) if len(m.effort) == len(m.name) else None
        js_ns.append(_stamp_ns(m.header))
        js_pos.append(pos)
        js_eff.append(eff)
    if not js_pos:
        raise BagError(f"{bag.name}: {topics.joint_states} has no usable message (all malformed)")
    order = np.argsort(js_ns, kind="stable")
    js_ns = np.asarray(js_ns, dtype=np.int64)[order]
    js_pos = np.stack(js_pos)[order]
    # efforts: only when every usable message has finite ones (else None: a rig without torque sensing)
    have_eff = all(e is not None and np.all(np.isfinite(e)) for e in js_eff)
    js_eff = np.stack([js_eff[i] for i in order]) if have_eff else None

    # ---- static transforms
    static_tf: dict[tuple[str, str], np.ndarray] = {}
    for m in raw[topics.tf_static]:
        for tr in m.transforms:
            static_tf[(tr.header.frame_id, tr.child_frame_id)] = tf_to_matrix(tr.transform)

    # ---- frame clock: the first camera's colour stamps
    cam0 = cameras[0]
    color0 = raw[topics.topic("color", cam0)]
    if not color0:
        raise BagError(f"{bag.name}: {topics.topic('color', cam0)} is empty")
    stamps = np.array(sorted(_stamp_ns(m.header) for m in color0), dtype=np.int64)
    if max_frames is not None:
        stamps = stamps[:max_frames]
    tol = int(sync_tolerance_ms * 1e6)

    # joint states interpolated per joint at frame stamps (held at the ends)
    if len(js_ns) == 1:
        q = np.repeat(js_pos, len(stamps), axis=0)
    else:
        q = np.stack([np.interp(stamps, js_ns, js_pos[:, j]) for j in range(len(names))], axis=-1)
    tau = None
    if js_eff is not None:
        tau = (np.repeat(js_eff, len(stamps), axis=0) if len(js_ns) == 1 else
               np.stack([np.interp(stamps, js_ns, js_eff[:, j]) for j in range(len(names))], axis=-1))
    if stamps[0] < js_ns[0] - tol or stamps[-1] > js_ns[-1] + tol:
        raise BagError(f"{bag.name}: {topics.joint_states} does not cover the camera frames")

    streams: dict[str, CameraStream] = {}
    for cam in cameras:
        infos = raw[topics.topic("camera_info", cam)]
        if not infos:
            raise BagError(f"{bag.name}: {topics.topic('camera_info', cam)} is empty")
        info = infos[0]
        K = np.asarray(info.k, dtype=np.float64).reshape(3, 3)
        if K[0, 0] <= 0 or K[1, 1] <= 0:
            raise BagError(f"{bag.name}: {topics.topic('camera_info', cam)} has no intrinsics (K[0,0] = {K[0, 0]})")

        def stack(kind: str, allowed: Sequence[str], optional: bool = False):
            t = topics.topic(kind, cam)
            msgs = raw.get(t, [])
            if not msgs:
                if optional:
                    return None, None
                raise BagError(f"{bag.name}: {t} is empty")
            msgs = sorted(msgs, key=lambda m: _stamp_ns(m.header))
            ns = np.array([_stamp_ns(m.header) for m in msgs], dtype=np.int64)
            pick = _nearest(ns, stamps, tol, t)
            arrs = [decode_image(msgs[i], t, allowed) for i in pick]
            shape = arrs[0].shape
            if any(a.shape != shape for a in arrs):
                raise BagError(f"{t}: image size changes within the episode")
            return np.stack(arrs), msgs[pick[0]].header.frame_id

        rgb, frame_id = stack("color", ("rgb8", "bgr8"))
        depth_raw, _ = stack("depth", ("16uc1", "mono16", "32fc1"))
        if depth_raw.dtype == np.uint16:
            depth = depth_raw.astype(np.float32) / 1000.0
        else:
            depth = np.nan_to_num(depth_raw.astype(np.float32), nan=0.0, posinf=0.0, neginf=0.0)
        om, _ = stack("object_mask", ("mono8", "8uc1"), optional=not require_masks)
        rm, _ = stack("robot_mask", ("mono8", "8uc1"), optional=True)
        H, W = rgb.shape[1:3]
        if (int(info.width), int(info.height)) != (W, H):
            raise BagError(f"{topics.topic('camera_info', cam)}: {info.width}x{info.height} != image {W}x{H}")
        for name, a in (("depth", depth), ("object_mask", om), ("robot_mask", rm)):
            if a is not None and a.shape[1:3] != (H, W):
                raise BagError(f"{topics.topic(name, cam)}: {a.shape[2]}x{a.shape[1]} != colour {W}x{H}")
        streams[cam] = CameraStream(
            name=cam, frame_id=frame_id or info.header.frame_id, K=K, width=W, height=H, rgb=rgb, depth=depth,
            object_mask=None if om is None else om > 127, robot_mask=None if rm is None else rm > 127,
        )
    return Episode(path=bag, stamps_ns=stamps, joint_names=names, joint_positions=q, cameras=streams, static_tf=static_tf,
                   joint_efforts=tau)


# ------------------------------------------------------------ camera poses
def _tf_parents(static_tf: dict) -> dict[str, tuple[str, np.ndarray]]:
    parents: dict[str, tuple[str, np.ndarray]] = {}
    for (parent, child), T in static_tf.items():
        parents[child] = (parent, T)
    return parents


def resolve_camera_poses(
    episode: Episode,
    link_poses: Optional[Callable[[list[str], np.ndarray], dict[str, np.ndarray]]] = None,
    robot_base: Optional[str] = None,
    world_frame: str = "world",
) -> None:
    """Fill each camera's ``cam_to_world`` [T, 4, 4].

    A camera's chain of /tf_static parents is followed until it reaches
    `world_frame` (a fixed camera) or a robot link (a wrist camera). For a robot
    link L, ``world <- L`` is ``world <- base`` (tf_static) times FK ``base <- L``
    from `link_poses(joint_names, positions [T, J]) -> {link: [T, 4, 4]}`.
    """
    parents = _tf_parents(episode.static_tf)

    def chain_to(frame: str, stop: set[str]) -> tuple[str, np.ndarray]:
        T = np.eye(4)
        seen = set()
        while frame not in stop:
            if frame in seen or frame not in parents:
                raise BagError(f"{episode.path.name}: frame '{frame}' has no path to '{world_frame}' in /tf_static")
            seen.add(frame)
            parent, T_pc = parents[frame]
            T = T_pc @ T
            frame = parent
        return frame, T

    fk_cache: Optional[dict[str, np.ndarray]] = None
    for cam in episode.cameras.values():
        frame, T_top_cam = camera_mount(episode, cam.name, world_frame)
        if frame == world_frame:
            cam.cam_to_world = np.repeat(T_top_cam[None], episode.num_frames, axis=0)
            continue
        if link_poses is None or robot_base is None:
            raise BagError(f"{episode.path.name}: camera frame '{cam.frame_id}' hangs off '{frame}', "
                           f"not '{world_frame}': a robot model is needed to place it")
        if fk_cache is None:
            fk_cache = link_poses(episode.joint_names, episode.joint_positions)
        if frame not in fk_cache:
            raise BagError(f"{episode.path.name}: camera '{cam.name}' is mounted on '{frame}', "
                           "which is neither in /tf_static nor a link of the robot")
        _, T_world_base = chain_to(robot_base, {world_frame})
        cam.cam_to_world = T_world_base[None] @ fk_cache[frame] @ T_top_cam[None]


def camera_mount(episode: Episode, cam: str, world_frame: str = "world") -> tuple[str, np.ndarray]:
    """(top frame, T_top_cam [4, 4]): follow the camera's /tf_static parents up to
    `world_frame` (a fixed camera: top = world) or to the first frame without a
    static parent (a camera mounted on that robot link, e.g. a wrist camera)."""
    if cam not in episode.cameras:
        raise BagError(f"{episode.path.name}: no camera '{cam}' (have: {', '.join(episode.cameras)})")
    parents = _tf_parents(episode.static_tf)
    frame, T_top_cam, seen = episode.cameras[cam].frame_id, np.eye(4), set()
    if not frame:
        raise BagError(f"{episode.path.name}: camera '{cam}' images have an empty header.frame_id")
    while frame != world_frame and frame in parents:
        if frame in seen:
            raise BagError(f"{episode.path.name}: /tf_static has a cycle through '{frame}'")
        seen.add(frame)
        parent, T_pc = parents[frame]
        T_top_cam = T_pc @ T_top_cam
        frame = parent
    return frame, T_top_cam


def world_from_base(episode: Episode, robot_base: str, world_frame: str = "world") -> np.ndarray:
    """T_world_base [4, 4] from /tf_static (a BagError naming the frame when there is no path)."""
    parents = _tf_parents(episode.static_tf)
    frame, T, seen = robot_base, np.eye(4), set()
    while frame != world_frame:
        if frame in seen or frame not in parents:
            raise BagError(f"{episode.path.name}: frame '{frame}' has no path to '{world_frame}' in /tf_static")
        seen.add(frame)
        parent, T_pc = parents[frame]
        T = T_pc @ T
        frame = parent
    return T
