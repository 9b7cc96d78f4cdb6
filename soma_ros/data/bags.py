"""Read a recorded episode (rosbag2, sqlite3 or mcap) into synchronised arrays.

Topic conventions are those of a RealSense rig (remappable through
:class:`TopicConfig`; ``{cam}`` stands for a camera's namespace, which may be
nested, e.g. ``front`` or ``rig/front``):

  /joint_states                                sensor_msgs/JointState
  /{cam}/color/image_raw                       sensor_msgs/Image rgb8 or bgr8
  /{cam}/color/image_raw/compressed            sensor_msgs/CompressedImage (jpeg / png)
  /{cam}/color/camera_info                     sensor_msgs/CameraInfo (or the one below)
  /{cam}/aligned_depth_to_color/camera_info    sensor_msgs/CameraInfo
  /{cam}/aligned_depth_to_color/image_raw      sensor_msgs/Image 16UC1 (mm) or 32FC1 (m)
  /{cam}/object_mask, /{cam}/robot_mask        sensor_msgs/Image mono8 (optional)
  /tf_static, /tf                              tf2_msgs/TFMessage

Cameras are discovered from the topics present (:func:`discover_cameras`): a
camera is a namespace with a colour stream (raw or compressed) and an aligned
depth stream. Its name is the last component of the namespace (the whole
namespace with ``/`` -> ``_`` when two cameras share a last component).

Frames are synchronised on the colour image stamps of the first camera; every
other stream is matched to the nearest stamp within a tolerance, joint states
are interpolated linearly by stamp (their efforts too, when every message has one
per joint: :attr:`Episode.joint_efforts`). The evaluation-only ground-truth topic
``/world/object_points`` is never deserialised here (see
:data:`FORBIDDEN_TOPICS`); training code reads bags only through this module.

Transforms: /tf_static edges are fixed; /tf edges are kept as time series
(:attr:`Episode.dynamic_tf`) and sampled at the frame stamps, except for the
links of the robot, which are placed by the URDF's FK from the joint states.

Errors are :class:`BagError`, one line naming the bag and the topic: a missing
topic, a wrong encoding, an empty /joint_states, a frame with no TF path, streams
out of sync, an empty, truncated or corrupt bag file.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Optional, Sequence

import numpy as np

#: topics that training code must never read (evaluation-only ground truth)
FORBIDDEN_TOPICS = ("/world/object_points",)

IMAGE_TYPE = "sensor_msgs/msg/Image"
COMPRESSED_TYPE = "sensor_msgs/msg/CompressedImage"
INFO_TYPE = "sensor_msgs/msg/CameraInfo"


class BagError(ValueError):
    """A bag that cannot be used for training, with a one-line reason."""


def _one_line(exc: BaseException) -> str:
    s = " ".join(str(exc).split())
    return (s[:160] + "...") if len(s) > 160 else s


@dataclass
class TopicConfig:
    """Topic names of a rig; `{cam}` is replaced by each camera's namespace.

    ``color`` may also be recorded as ``color + compressed_suffix``
    (sensor_msgs/CompressedImage). ``camera_info`` falls back to
    ``depth_camera_info``. ``tf`` is read when present.
    """

    joint_states: str = "/joint_states"
    color: str = "/{cam}/color/image_raw"
    camera_info: str = "/{cam}/color/camera_info"
    depth: str = "/{cam}/aligned_depth_to_color/image_raw"
    depth_camera_info: str = "/{cam}/aligned_depth_to_color/camera_info"
    object_mask: str = "/{cam}/object_mask"
    robot_mask: str = "/{cam}/robot_mask"
    tf_static: str = "/tf_static"
    tf: str = "/tf"
    compressed_suffix: str = "/compressed"
    world_frame: str = "world"

    def topic(self, kind: str, cam: str) -> str:
        return getattr(self, kind).format(cam=cam)


@dataclass
class CameraTopics:
    """The topics of one discovered camera (``None``: not recorded)."""

    name: str
    namespace: str
    color: Optional[str]
    color_compressed: bool
    camera_info: Optional[str]
    depth: Optional[str]
    object_mask: Optional[str] = None
    robot_mask: Optional[str] = None

    def problems(self) -> list[str]:
        out = []
        if self.color is None:
            out.append(f"camera '{self.name}': no colour topic (raw or compressed)")
        if self.camera_info is None:
            out.append(f"camera '{self.name}': no camera_info topic (looked for color/ and aligned_depth_to_color/)")
        if self.depth is None:
            out.append(f"camera '{self.name}': no aligned depth topic")
        return out


def _pattern_keys(pattern: str, topics: dict[str, str], suffix: str = "") -> dict[str, str]:
    """{namespace: topic} for the topics that match ``pattern`` (+ ``suffix``)."""
    head, tail = pattern.split("{cam}")[0], pattern.split("{cam}")[-1] + suffix
    out = {}
    for t in topics:
        if t.startswith(head) and t.endswith(tail) and len(t) > len(head) + len(tail) and t not in FORBIDDEN_TOPICS:
            key = t[len(head): len(t) - len(tail)]
            if key and not key.startswith("/") and not key.endswith("/"):
                out[key] = t
    return out


def discover_cameras(topics: dict[str, str], cfg: Optional[TopicConfig] = None) -> dict[str, CameraTopics]:
    """Cameras of a bag from its ``{topic: msgtype}`` (see the module docstring), by name.

    A camera is any namespace with a colour stream; its other topics are looked up in the
    same namespace (missing ones are None: :meth:`CameraTopics.problems`)."""
    cfg = cfg or TopicConfig()
    raw = {k: t for k, t in _pattern_keys(cfg.color, topics).items() if topics[t] == IMAGE_TYPE}
    comp = {k: t for k, t in _pattern_keys(cfg.color, topics, cfg.compressed_suffix).items()
            if topics[t] == COMPRESSED_TYPE}
    # a namespace with depth or camera info but no colour is a camera whose colour is missing
    others = {k for kind in ("depth", "camera_info", "depth_camera_info")
              for k, t in _pattern_keys(getattr(cfg, kind), topics).items() if topics[t] in (IMAGE_TYPE, INFO_TYPE)}
    keys = sorted(set(raw) | set(comp) | others)
    last = [k.split("/")[-1] for k in keys]
    out: dict[str, CameraTopics] = {}
    for k, short in zip(keys, last):
        name = short if last.count(short) == 1 else k.replace("/", "_")

        def have(kind: str, types: Sequence[str]) -> Optional[str]:
            t = cfg.topic(kind, k)
            return t if topics.get(t) in types else None

        info = have("camera_info", (INFO_TYPE,)) or have("depth_camera_info", (INFO_TYPE,))
        out[name] = CameraTopics(
            name=name, namespace=k, color=raw.get(k) or comp.get(k), color_compressed=k not in raw and k in comp,
            camera_info=info,
            depth=have("depth", (IMAGE_TYPE,)), object_mask=have("object_mask", (IMAGE_TYPE,)),
            robot_mask=have("robot_mask", (IMAGE_TYPE,)),
        )
    return out


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
    topics: Optional[CameraTopics] = None


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
    #: /tf edges (parent, child) -> [T, 4, 4] float64 sampled at stamps_ns (nearest message)
    dynamic_tf: dict[tuple[str, str], np.ndarray] = field(default_factory=dict)

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


def decode_compressed(msg, topic: str, color: bool = True) -> np.ndarray:
    """sensor_msgs/CompressedImage (jpeg / png) -> [H, W, 3] uint8 RGB (``color``) or [H, W] uint8."""
    import cv2

    buf = np.asarray(msg.data, dtype=np.uint8)
    img = cv2.imdecode(buf, cv2.IMREAD_COLOR if color else cv2.IMREAD_GRAYSCALE) if buf.size else None
    if img is None:
        raise BagError(f"{topic}: a CompressedImage ({msg.format or 'no format'}) could not be decoded")
    return np.ascontiguousarray(img[..., ::-1]) if color else img


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


def nearest_index(src_ns: np.ndarray, query_ns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(index into sorted ``src_ns`` of the nearest stamp to each query, |error| ns), both [Q]."""
    idx = np.clip(np.searchsorted(src_ns, query_ns), 1, max(len(src_ns) - 1, 1))
    lo = np.clip(idx - 1, 0, len(src_ns) - 1)
    hi = np.clip(idx, 0, len(src_ns) - 1)
    pick = np.where(np.abs(src_ns[lo] - query_ns) <= np.abs(src_ns[hi] - query_ns), lo, hi)
    return pick, np.abs(src_ns[pick] - query_ns)


def _nearest(src_ns: np.ndarray, query_ns: np.ndarray, tol_ns: int, topic: str, bag: str = "") -> np.ndarray:
    pick, err = nearest_index(src_ns, query_ns)
    if (err > tol_ns).any():
        worst = int(err.max()) / 1e6
        where = f"{bag}: " if bag else ""
        raise BagError(f"{where}{topic}: not synchronised: no message within {tol_ns / 1e6:.1f} ms of "
                       f"{int((err > tol_ns).sum())} frame(s) (worst {worst:.1f} ms)")
    return pick


# ------------------------------------------------------------------ reading
def open_reader(bag: Path):
    """An opened rosbags AnyReader (a BagError naming the bag when it is missing, empty or corrupt)."""
    from rosbags.highlevel import AnyReader

    from soma_ros.bagtypes import typestore

    bag = Path(bag)
    if not bag.exists():
        raise BagError(f"bag not found: {bag}")
    reader = AnyReader([bag], default_typestore=typestore())
    try:
        reader.open()
    except Exception as exc:  # rosbags raises assorted reader / storage / sqlite / yaml errors
        raise BagError(f"{bag.name}: unreadable bag ({type(exc).__name__}: {_one_line(exc)})") from None
    return reader


def check_interface_versions(reader, bag: Path, package: str = "soma_msgs") -> None:
    """Refuse, in one BagError naming the bag and the topic, a ``package`` message type that
    the bag's recorder defined differently from this install (another soma_msgs version):
    its RIHS01 type hash differs, or this install has no such type. Bags that carry no
    RIHS01 hash (rosbag2 before Iron) are not checked."""
    from soma_ros.bagtypes import typestore

    store = typestore()
    for conn in reader.connections:
        if not conn.msgtype.startswith(f"{package}/"):
            continue
        differs = conn.msgtype not in store.types
        digest = getattr(conn, "digest", "") or ""
        if not differs and digest.startswith("RIHS01_"):
            differs = digest != store.hash_rihs01(conn.msgtype)
        if differs:
            raise BagError(f"{Path(bag).name}: {conn.topic} [{conn.msgtype}] was recorded with another {package} "
                           f"version than this install's; read it with the soma_ros that recorded it, or record it again")


def list_topics(bag: Path) -> dict[str, str]:
    reader = open_reader(Path(bag))
    try:
        return {c.topic: c.msgtype for c in reader.connections}
    finally:
        reader.close()


def _select_cameras(found: dict[str, CameraTopics], cameras: Optional[Sequence[str]], bag: Path,
                    topics: TopicConfig) -> list[CameraTopics]:
    if not found:
        raise BagError(f"{bag.name}: no camera topics matching {topics.color} (raw or {topics.compressed_suffix})")
    if cameras is None:
        return [found[n] for n in sorted(found)]
    by_ns = {c.namespace: c for c in found.values()}
    out = []
    for c in cameras:
        ct = found.get(c) or by_ns.get(c)
        if ct is None:
            raise BagError(f"{bag.name}: missing topic {topics.topic('color', c)} "
                           f"(camera '{c}'; cameras found: {', '.join(sorted(found))})")
        out.append(ct)
    return out


def read_episode(
    bag: str | Path,
    cameras: Optional[Sequence[str]] = None,
    topics: Optional[TopicConfig] = None,
    sync_tolerance_ms: float = 20.0,
    require_masks: bool = False,
    max_frames: Optional[int] = None,
) -> Episode:
    """Read one episode bag. ``cameras=None`` uses every discovered camera (:func:`discover_cameras`);
    else names or namespaces. ``require_masks``: an object-mask topic per camera is required
    (else cameras without one get ``object_mask = None``)."""
    topics = topics or TopicConfig()
    bag = Path(bag)
    reader = open_reader(bag)
    try:
        by_topic = {c.topic: c for c in reader.connections}
        types = {t: c.msgtype for t, c in by_topic.items()}
        if sum(int(c.msgcount) for c in reader.connections) == 0:
            raise BagError(f"{bag.name}: the bag holds no messages")
        cams = _select_cameras(discover_cameras(types, topics), cameras, bag, topics)
        needed = [topics.joint_states]
        for ct in cams:
            needed.append(ct.color or topics.topic("color", ct.namespace))
            if ct.camera_info is None:
                needed.append(topics.topic("camera_info", ct.namespace))
            if ct.depth is None:
                needed.append(topics.topic("depth", ct.namespace))
            if require_masks:
                needed.append(ct.object_mask or topics.topic("object_mask", ct.namespace))
        missing = [t for t in needed if t not in by_topic]
        if missing:
            raise BagError(f"{bag.name}: missing topic {missing[0]}" + (f" (+{len(missing) - 1} more)" if len(missing) > 1 else ""))
        wanted = {topics.joint_states} | {t for t in (topics.tf_static, topics.tf) if t in by_topic}
        for ct in cams:
            wanted |= {t for t in (ct.color, ct.camera_info, ct.depth, ct.object_mask, ct.robot_mask) if t}
        wanted -= set(FORBIDDEN_TOPICS)
        conns = [by_topic[t] for t in wanted]

        raw: dict[str, list] = {t: [] for t in wanted}
        try:
            for conn, _t, data in reader.messages(connections=conns):
                raw[conn.topic].append(reader.deserialize(data, conn.msgtype))
        except Exception as exc:  # a truncated or corrupt storage file
            raise BagError(f"{bag.name}: unreadable bag, stopped while reading messages "
                           f"({type(exc).__name__}: {_one_line(exc)})") from None
    finally:
        reader.close()

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
    for m in raw.get(topics.tf_static, []):
        for tr in m.transforms:
            static_tf[(tr.header.frame_id, tr.child_frame_id)] = tf_to_matrix(tr.transform)

    # ---- frame clock: the first camera's colour stamps
    color0 = raw[cams[0].color]
    if not color0:
        raise BagError(f"{bag.name}: {cams[0].color} is empty")
    stamps = np.array(sorted(_stamp_ns(m.header) for m in color0), dtype=np.int64)
    if max_frames is not None:
        stamps = stamps[:max_frames]
    tol = int(sync_tolerance_ms * 1e6)

    # ---- dynamic transforms, sampled at the frame stamps
    dyn: dict[tuple[str, str], list] = {}
    for m in raw.get(topics.tf, []):
        for tr in m.transforms:
            dyn.setdefault((tr.header.frame_id, tr.child_frame_id), []).append((_stamp_ns(tr.header), tr.transform))
    dynamic_tf: dict[tuple[str, str], np.ndarray] = {}
    for edge, items in dyn.items():
        if edge in static_tf:
            continue
        items.sort(key=lambda x: x[0])
        ns = np.array([s for s, _ in items], dtype=np.int64)
        pick, _err = nearest_index(ns, stamps)
        mats = np.stack([tf_to_matrix(items[i][1]) for i in pick])
        dynamic_tf[edge] = mats

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
        raise BagError(f"{bag.name}: {topics.joint_states}: not synchronised: it does not cover the camera frames "
                       f"({(js_ns[0] - stamps[0]) / 1e6:+.0f} ms at the start, {(stamps[-1] - js_ns[-1]) / 1e6:+.0f} ms at the end)")

    streams: dict[str, CameraStream] = {}
    for ct in cams:
        infos = raw[ct.camera_info]
        if not infos:
            raise BagError(f"{bag.name}: {ct.camera_info} is empty")
        info = infos[0]
        K = np.asarray(info.k, dtype=np.float64).reshape(3, 3)
        if K[0, 0] <= 0 or K[1, 1] <= 0:
            raise BagError(f"{bag.name}: {ct.camera_info} has no intrinsics (K[0,0] = {K[0, 0]})")

        def stack(t: Optional[str], allowed: Sequence[str], compressed: bool = False, color: bool = True):
            msgs = raw.get(t, []) if t else []
            if not msgs:
                if t is None:
                    return None, None
                raise BagError(f"{bag.name}: {t} is empty")
            msgs = sorted(msgs, key=lambda m: _stamp_ns(m.header))
            ns = np.array([_stamp_ns(m.header) for m in msgs], dtype=np.int64)
            pick = _nearest(ns, stamps, tol, t, bag.name)
            if compressed:
                arrs = [decode_compressed(msgs[i], f"{bag.name}: {t}", color) for i in pick]
            else:
                arrs = [decode_image(msgs[i], f"{bag.name}: {t}", allowed) for i in pick]
            shape = arrs[0].shape
            if any(a.shape != shape for a in arrs):
                raise BagError(f"{bag.name}: {t}: image size changes within the episode")
            return np.stack(arrs), msgs[pick[0]].header.frame_id

        rgb, frame_id = stack(ct.color, ("rgb8", "bgr8"), compressed=ct.color_compressed)
        depth_raw, depth_frame = stack(ct.depth, ("16uc1", "mono16", "32fc1"))
        if depth_raw.dtype == np.uint16:
            depth = depth_raw.astype(np.float32) / 1000.0
        else:
            depth = np.nan_to_num(depth_raw.astype(np.float32), nan=0.0, posinf=0.0, neginf=0.0)
        om, _ = stack(ct.object_mask, ("mono8", "8uc1"))
        rm, _ = stack(ct.robot_mask, ("mono8", "8uc1"))
        H, W = rgb.shape[1:3]
        if (int(info.width), int(info.height)) != (W, H):
            raise BagError(f"{bag.name}: {ct.camera_info}: {info.width}x{info.height} != image {W}x{H}")
        for t, a in ((ct.depth, depth), (ct.object_mask, om), (ct.robot_mask, rm)):
            if a is not None and a.shape[1:3] != (H, W):
                raise BagError(f"{bag.name}: {t}: {a.shape[2]}x{a.shape[1]} != colour {W}x{H}")
        streams[ct.name] = CameraStream(
            name=ct.name, frame_id=frame_id or depth_frame or info.header.frame_id, K=K, width=W, height=H, rgb=rgb,
            depth=depth, object_mask=None if om is None else om > 127, robot_mask=None if rm is None else rm > 127,
            topics=ct,
        )
    return Episode(path=bag, stamps_ns=stamps, joint_names=names, joint_positions=q, cameras=streams, static_tf=static_tf,
                   joint_efforts=tau, dynamic_tf=dynamic_tf)


# ------------------------------------------------------------ camera poses
def _tf_parents(static_tf: dict) -> dict[str, tuple[str, np.ndarray]]:
    parents: dict[str, tuple[str, np.ndarray]] = {}
    for (parent, child), T in static_tf.items():
        parents[child] = (parent, T)
    return parents


def _chain(episode: Episode, frame: str, stop: Callable[[str], bool]) -> tuple[str, np.ndarray]:
    """Follow /tf_static then /tf parents from ``frame`` until ``stop(frame)`` or a frame without a
    parent. Returns (top frame, T_top_frame [T, 4, 4])."""
    static = _tf_parents(episode.static_tf)
    dynamic = _tf_parents(episode.dynamic_tf)
    T = np.repeat(np.eye(4)[None], episode.num_frames, axis=0)
    seen: set[str] = set()
    while not stop(frame) and (frame in static or frame in dynamic):
        if frame in seen:
            raise BagError(f"{episode.path.name}: the TF tree has a cycle through '{frame}'")
        seen.add(frame)
        parent, T_pc = static[frame] if frame in static else dynamic[frame]
        T = T_pc @ T
        frame = parent
    return frame, T


def resolve_camera_poses(
    episode: Episode,
    link_poses: Optional[Callable[[list[str], np.ndarray], dict[str, np.ndarray]]] = None,
    robot_base: Optional[str] = None,
    world_frame: str = "world",
    robot_links: Optional[Sequence[str]] = None,
) -> None:
    """Fill each camera's ``cam_to_world`` [T, 4, 4].

    A camera's chain of /tf_static (then /tf) parents is followed until it reaches
    `world_frame` (a fixed camera) or a robot link (a wrist camera). For a robot
    link L, ``world <- L`` is ``world <- base`` (TF) times FK ``base <- L``
    from `link_poses(joint_names, positions [T, J]) -> {link: [T, 4, 4]}`.
    """
    fk_cache: Optional[dict[str, np.ndarray]] = None
    links = set(robot_links or ())
    for cam in episode.cameras.values():
        if not cam.frame_id:
            raise BagError(f"{episode.path.name}: camera '{cam.name}' images have an empty header.frame_id")
        frame, T_top_cam = _chain(episode, cam.frame_id, lambda f: f == world_frame or f in links)
        topic = cam.topics.color if cam.topics is not None else cam.name
        if frame == world_frame:
            cam.cam_to_world = T_top_cam
            continue
        if link_poses is None or robot_base is None:
            raise BagError(f"{episode.path.name}: {topic}: camera frame '{cam.frame_id}' has no TF path to "
                           f"'{world_frame}' (it ends at '{frame}'); a robot model is needed if that is a robot link")
        if fk_cache is None:
            fk_cache = link_poses(episode.joint_names, episode.joint_positions)
        if frame not in fk_cache:
            raise BagError(f"{episode.path.name}: {topic}: camera frame '{cam.frame_id}' has no TF path to "
                           f"'{world_frame}': it ends at '{frame}', which is not a link of the robot")
        T_world_base = world_from_base(episode, robot_base, world_frame)
        cam.cam_to_world = T_world_base[None] @ fk_cache[frame] @ T_top_cam


def camera_mount(episode: Episode, cam: str, world_frame: str = "world",
                 robot_links: Optional[Sequence[str]] = None) -> tuple[str, np.ndarray]:
    """(top frame, T_top_cam [4, 4]): follow the camera's TF parents up to `world_frame` (a fixed
    camera: top = world), to the first of ``robot_links`` or to the first frame without a parent
    (a camera mounted on that robot link, e.g. a wrist camera). The transform is the first frame's."""
    if cam not in episode.cameras:
        raise BagError(f"{episode.path.name}: no camera '{cam}' (have: {', '.join(episode.cameras)})")
    frame = episode.cameras[cam].frame_id
    if not frame:
        raise BagError(f"{episode.path.name}: camera '{cam}' images have an empty header.frame_id")
    links = set(robot_links or ())
    top, T = _chain(episode, frame, lambda f: f == world_frame or f in links)
    return top, T[0]


def world_from_base(episode: Episode, robot_base: str, world_frame: str = "world") -> np.ndarray:
    """T_world_base [4, 4] from /tf_static (or /tf, first frame); a BagError naming the frame when there is no path."""
    top, T = _chain(episode, robot_base, lambda f: f == world_frame)
    if top != world_frame:
        raise BagError(f"{episode.path.name}: frame '{robot_base}' has no path to '{world_frame}' in /tf_static or /tf "
                       f"(it ends at '{top}')")
    return T[0]
