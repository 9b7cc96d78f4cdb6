#!/usr/bin/env python3
"""Rewrite reference-world bags into the forms a real rig records, with rosbags.

    python tools/rig_bags.py SRC_DATASET OUT [--strip-masks] [--rename cam_front=front ...]
        [--compressed jpeg|png] [--namespace rig] [--bgr] [--depth-32f] [--info-from-depth]
        [--storage sqlite3|mcap] [--manifest none|plain|entries]

SRC_DATASET is a folder of bags (e.g. from `soma world`); every bag is rewritten into
OUT/<bag name>. The evaluation-only ``/world/object_points`` topic is dropped (kept only with
``RigForm.keep_ground_truth``, for comparisons such as ``tools/retarget_robot.py``).

* ``--strip-masks``: no ``/<cam>/object_mask`` / ``robot_mask`` topics.
* ``--rename OLD=NEW``: a camera's topics and frame ids (image headers, TF frames) renamed.
* ``--compressed``: colour as sensor_msgs/CompressedImage on ``.../color/image_raw/compressed``.
* ``--namespace NS``: topics ``/NS/<cam>/...`` (newer realsense2_camera layout).
* ``--bgr``: raw colour as bgr8; ``--depth-32f``: depth as 32FC1 metres.
* ``--info-from-depth``: only ``aligned_depth_to_color/camera_info`` (no ``color/camera_info``).
* ``--manifest``: none; ``plain`` ({"episodes": [names], "split": {...}}); ``entries``
  (the reference world's form).

The functions are also used by the tests to build broken bags (:func:`rewrite_bag` with
``alter`` / ``drop``, :func:`truncate_bag`, :func:`corrupt_bag`).
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Optional

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

MASK_SUFFIXES = ("/object_mask", "/robot_mask")
GROUND_TRUTH = "/world/object_points"


@dataclass
class RigForm:
    strip_masks: bool = False
    rename: dict[str, str] = field(default_factory=dict)
    compressed: Optional[str] = None  # "jpeg" | "png"
    namespace: Optional[str] = None
    bgr: bool = False
    depth_32f: bool = False
    info_from_depth: bool = False
    storage: str = "sqlite3"
    keep_ground_truth: bool = False  # keep /world/object_points (a comparison of two forms of one episode)


def _cam_of(topic: str, cams: set[str]) -> Optional[str]:
    parts = topic.strip("/").split("/")
    return parts[0] if parts and parts[0] in cams else None


def _rename_frame(frame: str, rename: dict[str, str]) -> str:
    for old, new in rename.items():
        if frame == old or frame.startswith(old + "_") or frame.startswith(old + "/"):
            return new + frame[len(old):]
    return frame


def rewrite_bag(src: Path, dst: Path, form: RigForm = RigForm(), drop: tuple[str, ...] = (),
                alter: Optional[Callable[[str, object], object]] = None, empty: bool = False) -> Path:
    """Copy bag ``src`` to ``dst`` in ``form``; topics in ``drop`` (after renaming) are left out;
    ``alter(topic, msg) -> msg`` may change messages (after the form's changes); ``empty``: only
    the connections, no message."""
    import cv2
    from rosbags.highlevel import AnyReader
    from rosbags.rosbag2 import StoragePlugin, Writer

    from soma_ros.bagtypes import typestore

    ts = typestore()
    plugin = {"sqlite3": StoragePlugin.SQLITE3, "mcap": StoragePlugin.MCAP}[form.storage]
    with AnyReader([Path(src)], default_typestore=ts) as r:
        cams = {c.topic.strip("/").split("/")[0] for c in r.connections if c.topic.endswith("/color/image_raw")}
        Img = ts.types["sensor_msgs/msg/Image"]
        Comp = ts.types["sensor_msgs/msg/CompressedImage"]

        def new_topic(topic: str) -> tuple[Optional[str], str]:
            """(new topic or None to drop, kind)."""
            if topic == GROUND_TRUTH and not form.keep_ground_truth:
                return None, ""
            cam = _cam_of(topic, cams)
            if cam is None:
                return topic, "other"
            rest = topic.strip("/")[len(cam):]
            if form.strip_masks and rest in MASK_SUFFIXES:
                return None, ""
            if form.info_from_depth and rest == "/color/camera_info":
                return None, ""
            name = form.rename.get(cam, cam)
            ns = f"/{form.namespace}" if form.namespace else ""
            out = f"{ns}/{name}{rest}"
            if rest == "/color/image_raw":
                return (out + "/compressed", "compressed") if form.compressed else (out, "color")
            if rest == "/aligned_depth_to_color/image_raw":
                return out, "depth"
            return out, "camera"

        with Writer(Path(dst), version=9, storage_plugin=plugin) as w:
            conns, kinds = {}, {}
            extra_info = {}
            source_topics = {c.topic for c in r.connections}
            for c in r.connections:
                t, kind = new_topic(c.topic)
                if t is None or t in drop:
                    continue
                mt = "sensor_msgs/msg/CompressedImage" if kind == "compressed" else c.msgtype
                conns[c.id] = w.add_connection(t, mt, typestore=ts)
                kinds[c.id] = (t, kind)
                has_depth_info = c.topic.replace("/image_raw", "/camera_info") in source_topics
                if form.info_from_depth and c.topic.endswith("/aligned_depth_to_color/image_raw") \
                        and not has_depth_info:  # the bag records none of its own: made from the colour one
                    it = t.replace("/image_raw", "/camera_info")
                    if it not in drop:
                        extra_info[c.topic.replace("/aligned_depth_to_color/image_raw", "/color/camera_info")] = \
                            w.add_connection(it, "sensor_msgs/msg/CameraInfo", typestore=ts)
            if empty:
                return Path(dst)
            for c, stamp, raw in r.messages():
                if c.topic in extra_info:
                    msg = r.deserialize(raw, c.msgtype)
                    msg.header.frame_id = _rename_frame(msg.header.frame_id, form.rename)
                    w.write(extra_info[c.topic], stamp, ts.serialize_cdr(msg, c.msgtype))
                if c.id not in conns:
                    continue
                t, kind = kinds[c.id]
                msg = r.deserialize(raw, c.msgtype)
                mt = c.msgtype
                if hasattr(msg, "header"):
                    msg.header.frame_id = _rename_frame(msg.header.frame_id, form.rename)
                if hasattr(msg, "transforms"):
                    for tr in msg.transforms:
                        tr.header.frame_id = _rename_frame(tr.header.frame_id, form.rename)
                        tr.child_frame_id = _rename_frame(tr.child_frame_id, form.rename)
                if kind in ("color", "compressed"):
                    rgb = np.asarray(msg.data, np.uint8).reshape(msg.height, msg.step)[:, : msg.width * 3]
                    rgb = rgb.reshape(msg.height, msg.width, 3)
                    if msg.encoding.lower() == "bgr8":
                        rgb = rgb[..., ::-1]
                    if kind == "compressed":
                        ext = ".jpg" if form.compressed == "jpeg" else ".png"
                        ok, buf = cv2.imencode(ext, np.ascontiguousarray(rgb[..., ::-1]))
                        assert ok
                        msg = Comp(header=msg.header, format=f"rgb8; {form.compressed} compressed bgr8",
                                   data=np.frombuffer(buf.tobytes(), np.uint8))
                        mt = "sensor_msgs/msg/CompressedImage"
                    elif form.bgr:
                        msg = Img(header=msg.header, height=msg.height, width=msg.width, encoding="bgr8",
                                  is_bigendian=0, step=msg.width * 3,
                                  data=np.ascontiguousarray(rgb[..., ::-1]).reshape(-1))
                elif kind == "depth" and form.depth_32f and msg.encoding.lower() == "16uc1":
                    d = np.asarray(msg.data, np.uint8).view("<u2").reshape(msg.height, msg.width).astype(np.float32) / 1000.0
                    msg = Img(header=msg.header, height=msg.height, width=msg.width, encoding="32FC1",
                              is_bigendian=0, step=msg.width * 4, data=d.reshape(-1).view(np.uint8))
                if alter is not None:
                    msg = alter(t, msg)
                    if msg is None:
                        continue
                w.write(conns[c.id], stamp, ts.serialize_cdr(msg, mt))
    return Path(dst)


def storage_file(bag: Path) -> Path:
    files = sorted(p for p in Path(bag).iterdir() if p.suffix in (".db3", ".mcap"))
    if not files:
        raise FileNotFoundError(f"{bag}: no .db3 / .mcap file")
    return files[0]


def truncate_bag(bag: Path, keep: float = 0.5) -> Path:
    """Cut the bag's storage file to ``keep`` of its size (a recording that was killed)."""
    f = storage_file(bag)
    data = f.read_bytes()
    f.write_bytes(data[: int(len(data) * keep)])
    return bag


def corrupt_bag(bag: Path, offset: float = 0.0, length: int = 4096) -> Path:
    """Overwrite ``length`` bytes of the storage file at ``offset`` (fraction of its size) with garbage."""
    f = storage_file(bag)
    data = bytearray(f.read_bytes())
    o = int(len(data) * offset)
    data[o: o + length] = bytes((i * 37 + 11) % 256 for i in range(min(length, len(data) - o)))
    f.write_bytes(bytes(data))
    return bag


def write_manifest(out: Path, names: list[str], form: str, test_fraction: float = 0.3) -> None:
    if form == "none":
        return
    k = max(1, int(round(test_fraction * len(names)))) if len(names) > 1 else 0
    test, train = names[len(names) - k:], names[: len(names) - k]
    if form == "plain":
        doc = {"episodes": names, "split": {"train": train, "test": test}}
    else:
        doc = {"episodes": [{"name": n, "bag": n, "split": "test" if n in test else "train"} for n in names]}
    (out / "manifest.json").write_text(json.dumps(doc, indent=1))


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("src")
    p.add_argument("out")
    p.add_argument("--strip-masks", action="store_true")
    p.add_argument("--rename", action="append", default=[], metavar="OLD=NEW")
    p.add_argument("--compressed", choices=["jpeg", "png"], default=None)
    p.add_argument("--namespace", default=None)
    p.add_argument("--bgr", action="store_true")
    p.add_argument("--depth-32f", action="store_true")
    p.add_argument("--info-from-depth", action="store_true")
    p.add_argument("--storage", choices=["sqlite3", "mcap"], default="sqlite3")
    p.add_argument("--manifest", choices=["none", "plain", "entries"], default="none")
    a = p.parse_args(argv)
    from soma_ros.data.sources import find_bags, is_bag

    src = Path(a.src)
    bags = [src] if is_bag(src) else find_bags(src)
    if not bags:
        print(f"rig_bags: no bag in {src}", file=sys.stderr)
        return 1
    rename = dict(x.split("=", 1) for x in a.rename)
    form = RigForm(a.strip_masks, rename, a.compressed, a.namespace, a.bgr, a.depth_32f, a.info_from_depth, a.storage)
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    names = []
    for b in bags:
        rewrite_bag(b, out / b.name, form)
        names.append(b.name)
        print(f"rig_bags: {b} -> {out / b.name}")
    write_manifest(out, names, a.manifest)
    return 0


if __name__ == "__main__":
    sys.exit(main())
