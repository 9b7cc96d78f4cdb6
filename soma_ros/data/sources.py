"""What ``--data`` may name, and which of its bags are usable.

``--data`` is one of:

* a **folder with a manifest** (``manifest.json``) in one of two forms::

      {"episodes": [{"name": "ep0", "bag": "ep0", "split": "train", "task": "lift"}, ...]}
      {"episodes": ["ep0", "ep1", ...], "split": {"train": ["ep0"], "test": ["ep1"]}}

  (``bag`` defaults to the name; a bag path is relative to the folder; the second form
  without ``split`` gets the default split below);
* a **folder of recordings without a manifest**: every rosbag2 directory below it
  (a folder with ``metadata.yaml``; sqlite3 or mcap; any names), in sorted order, named
  by its path relative to the folder. The split is :func:`default_split`;
* **one bag**, or **several bags** named one by one: their episodes serve whichever split
  is asked for (split ``*``).

:func:`default_split`: the sorted names are shuffled with ``numpy.random.default_rng(seed)``
(seed 0 by default) and the first ``round(fraction * n)`` (fraction 0.3 by default; at
least one when there are two or more bags, never all of them) are the test split.
:func:`write_split` records the split that a run used in ``RUN/split.json``.

:func:`probe_bag` checks a bag without decoding its images (a corrupt, truncated or
empty file, missing joint states, joint names the URDF lacks, cameras without
camera_info / depth / a TF path, streams out of sync) and returns every problem, one
line each. :func:`usable_episodes` lists and skips bad bags (or stops at the first one
with ``strict``).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Optional, Sequence, Union

import numpy as np

from soma_ros.data.bags import BagError, TopicConfig, discover_cameras, open_reader

__all__ = ["MANIFEST", "ANY_SPLIT", "EpisodeRef", "load_dataset", "find_bags", "default_split", "write_split",
           "probe_bag", "BagProbe", "usable_episodes", "manifest_forms"]

MANIFEST = "manifest.json"
#: the split of bags named one by one: they serve every split
ANY_SPLIT = "*"

manifest_forms = ('{"episodes": [{"name": ..., "bag": ..., "split": ...}, ...]} or '
                  '{"episodes": [names], "split": {"train": [...], "test": [...]}}')


@dataclass
class EpisodeRef:
    """One episode: ``bag`` is the absolute bag directory."""

    name: str
    bag: Path
    split: str
    task: Optional[str] = None
    frames: Optional[int] = None

    def in_split(self, split: Optional[str]) -> bool:
        return split is None or self.split == ANY_SPLIT or self.split == split


def is_bag(path: Path) -> bool:
    return path.is_dir() and (path / "metadata.yaml").is_file()


def find_bags(folder: Path) -> list[Path]:
    """rosbag2 directories below ``folder`` (not inside another bag), sorted by relative path."""
    out: list[Path] = []

    def walk(d: Path) -> None:
        for c in sorted(p for p in d.iterdir() if p.is_dir()):
            if is_bag(c):
                out.append(c)
            else:
                walk(c)

    walk(folder)
    return out


def default_split(names: Sequence[str], fraction: float = 0.3, seed: int = 0) -> dict[str, str]:
    """{name: "train" | "test"}: see the module docstring."""
    names = sorted(names)
    n = len(names)
    k = int(round(fraction * n))
    if n >= 2 and fraction > 0:
        k = min(max(k, 1), n - 1)
    else:
        k = 0
    perm = np.random.default_rng(seed).permutation(n)
    test = {names[i] for i in perm[:k]}
    return {nm: ("test" if nm in test else "train") for nm in names}


def _read_manifest(d: Path) -> dict:
    m = d / MANIFEST
    try:
        data = json.loads(m.read_text())
    except json.JSONDecodeError as exc:
        raise ValueError(f"{m}: invalid JSON ({exc.msg} at line {exc.lineno})") from None
    if not isinstance(data, dict) or not isinstance(data.get("episodes"), list):
        raise ValueError(f"{m}: expected {manifest_forms}")
    return data


def _manifest_refs(d: Path, fraction: float, seed: int) -> list[EpisodeRef]:
    m = d / MANIFEST
    data = _read_manifest(d)
    eps, splits = data["episodes"], data.get("split")
    if splits is not None and not (isinstance(splits, dict) and all(isinstance(v, list) for v in splits.values())):
        raise ValueError(f"{m}: 'split' must map split names to lists of episode names; expected {manifest_forms}")
    entries = []
    for i, e in enumerate(eps):
        if isinstance(e, str):
            entries.append({"name": e})
        elif isinstance(e, dict) and isinstance(e.get("name"), str):
            entries.append(e)
        else:
            raise ValueError(f"{m}: episodes[{i}] is neither a name nor an object with a 'name'; expected {manifest_forms}")
    names = [e["name"] for e in entries]
    if len(set(names)) != len(names):
        dup = next(n for n in names if names.count(n) > 1)
        raise ValueError(f"{m}: episode '{dup}' is listed twice")
    assign: dict[str, str] = {}
    if splits is not None:
        for sp, members in splits.items():
            for n in members:
                if n not in names:
                    raise ValueError(f"{m}: split '{sp}' names '{n}', which is not in 'episodes'")
                assign[n] = str(sp)
    elif not any("split" in e for e in entries):
        assign = default_split(names, fraction, seed)
    out = []
    for e in entries:
        bag = Path(str(e.get("bag", e["name"])))
        bag = bag if bag.is_absolute() else d / bag
        if not bag.exists():
            raise FileNotFoundError(f"{m}: bag of episode '{e['name']}' not found: {bag}")
        split = assign.get(e["name"], str(e.get("split", "")))
        out.append(EpisodeRef(e["name"], bag, split, e.get("task"), e.get("frames")))
    return out


def load_dataset(
    data: Union[str, Path, Sequence[Union[str, Path]]],
    split: Optional[str] = None,
    tasks: Optional[Sequence[str]] = None,
    test_fraction: float = 0.3,
    seed: int = 0,
) -> list[EpisodeRef]:
    """Episodes of ``data`` (module docstring), optionally of one split and of some tasks."""
    if isinstance(data, (list, tuple)) and len(data) == 1:
        data = data[0]
    if isinstance(data, (list, tuple)):
        refs, seen = [], set()
        for p in map(Path, data):
            if not is_bag(p):
                raise FileNotFoundError(f"not a rosbag2 directory (no metadata.yaml): {p}")
            name = p.name
            while name in seen:
                name = name + "_"
            seen.add(name)
            refs.append(EpisodeRef(name, p.resolve(), ANY_SPLIT))
    else:
        d = Path(data)
        if not d.exists():
            raise FileNotFoundError(f"dataset not found: {d}")
        if is_bag(d):
            refs = [EpisodeRef(d.name, d.resolve(), ANY_SPLIT)]
        elif not d.is_dir():
            raise FileNotFoundError(f"{d}: expected a folder of rosbag2 directories, a bag directory or several bags")
        elif (d / MANIFEST).is_file():
            refs = _manifest_refs(d, test_fraction, seed)
        else:
            bags = find_bags(d)
            if not bags:
                raise FileNotFoundError(f"{d}: no {MANIFEST} and no rosbag2 directory (a folder with metadata.yaml) in it")
            names = [str(b.relative_to(d)) for b in bags]
            assign = default_split(names, test_fraction, seed)
            refs = [EpisodeRef(n, b.resolve(), assign[n]) for n, b in zip(names, bags)]
    return [r for r in refs if r.in_split(split) and (tasks is None or r.task in tasks or r.split == ANY_SPLIT)]


def write_split(run_dir: Path, data, refs: Sequence[EpisodeRef], test_fraction: float, seed: int) -> Path:
    """``RUN/split.json``: the episodes (name, bag, split) a run read from ``data``."""
    run_dir = Path(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    src = [str(Path(p)) for p in data] if isinstance(data, (list, tuple)) else str(Path(data))
    doc = {"data": src, "test_fraction": test_fraction, "seed": seed,
           "rule": "no manifest: sorted bag names shuffled by numpy.random.default_rng(seed); "
                   "the first round(test_fraction * n) are 'test'",
           "episodes": [{"name": r.name, "bag": str(r.bag), "split": r.split} for r in refs]}
    out = run_dir / "split.json"
    tmp = out.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(doc, indent=1))
    tmp.replace(out)
    return out


# --------------------------------------------------------------------------- probing
@dataclass
class BagProbe:
    """What :func:`probe_bag` found in one bag (no image decoded)."""

    bag: Path
    topics: dict[str, str] = field(default_factory=dict)
    counts: dict[str, int] = field(default_factory=dict)
    cameras: dict = field(default_factory=dict)  # name -> soma_ros.data.bags.CameraTopics
    rates_hz: dict[str, float] = field(default_factory=dict)
    sync_ms: dict[str, float] = field(default_factory=dict)  # camera -> worst colour/depth gap to the frame clock
    joint_names: list[str] = field(default_factory=list)
    tf_paths: dict[str, str] = field(default_factory=dict)  # camera -> "world" / "link <name>" / "none (ends at f)"
    encodings: dict[str, str] = field(default_factory=dict)
    problems: list[str] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return not self.problems


def _header_stamp(raw: bytes, fallback: int) -> int:
    """header.stamp (ns) of a CDR-serialised message that starts with a std_msgs/Header (Image,
    CompressedImage), read without deserialising the pixels; ``fallback`` when it is not CDR."""
    if len(raw) < 12 or raw[0] != 0 or raw[1] not in (0, 1):
        return fallback
    order = "<" if raw[1] == 1 else ">"
    sec, nsec = np.frombuffer(raw[4:12], dtype=np.dtype(f"{order}i4")).astype(np.int64)
    return int(sec) * 1_000_000_000 + int(nsec) % (1 << 32)


def probe_bag(bag: Path, topics: Optional[TopicConfig] = None, robot=None, sync_tolerance_ms: float = 20.0,
              cameras: Optional[Sequence[str]] = None) -> BagProbe:
    """Check one bag (module docstring); every problem is one line naming the bag and the topic."""
    from soma_ros.data.bags import FORBIDDEN_TOPICS, nearest_index, tf_to_matrix

    topics = topics or TopicConfig()
    bag = Path(bag)
    pr = BagProbe(bag)
    name = bag.name
    try:
        reader = open_reader(bag)
    except BagError as exc:
        pr.problems.append(str(exc))
        return pr
    try:
        pr.topics = {c.topic: c.msgtype for c in reader.connections}
        for c in reader.connections:
            pr.counts[c.topic] = pr.counts.get(c.topic, 0) + int(c.msgcount)
        if sum(pr.counts.values()) == 0:
            pr.problems.append(f"{name}: the bag holds no messages (empty)")
            return pr
        found = discover_cameras(pr.topics, topics)
        if cameras is not None:
            found = {k: v for k, v in found.items() if k in cameras or v.namespace in cameras}
            for c in cameras:
                if c not in found and not any(v.namespace == c for v in found.values()):
                    pr.problems.append(f"{name}: missing topic {topics.topic('color', c)} (camera '{c}')")
        pr.cameras = found
        if not found:
            pr.problems.append(f"{name}: no camera topics matching {topics.color} (raw or {topics.compressed_suffix})")
        for ct in found.values():
            pr.problems += [f"{name}: {p}" for p in ct.problems()]
        small = {topics.joint_states, topics.tf_static, topics.tf} | {ct.camera_info for ct in found.values() if ct.camera_info}
        streams = {t for ct in found.values() for t in (ct.color, ct.depth) if t}
        keep_small = {t: [] for t in small if t in pr.topics}
        stamps: dict[str, list[int]] = {t: [] for t in streams}
        conns = [c for c in reader.connections if c.topic not in FORBIDDEN_TOPICS]
        try:
            for conn, ts, raw in reader.messages(connections=conns):
                if conn.topic in keep_small:
                    keep_small[conn.topic].append(reader.deserialize(raw, conn.msgtype))
                elif conn.topic in stamps:
                    stamps[conn.topic].append(_header_stamp(raw, int(ts)))
                    if conn.topic not in pr.encodings:
                        if conn.msgtype.endswith("CompressedImage"):
                            pr.encodings[conn.topic] = reader.deserialize(raw, conn.msgtype).format or "compressed"
                        else:
                            pr.encodings[conn.topic] = reader.deserialize(raw, conn.msgtype).encoding
        except Exception as exc:  # a truncated or corrupt storage file
            pr.problems.append(f"{name}: unreadable bag, stopped while reading messages ({type(exc).__name__}: "
                               f"{' '.join(str(exc).split())[:120]})")
            return pr
    finally:
        reader.close()

    js = keep_small.get(topics.joint_states)
    if js is None:
        pr.problems.append(f"{name}: missing topic {topics.joint_states} (no joint states)")
    elif not js:
        pr.problems.append(f"{name}: {topics.joint_states} is empty")
    else:
        pr.joint_names = [str(n) for n in js[0].name]
        if robot is not None:
            try:
                robot.q_from_joint_state(pr.joint_names, np.zeros((1, len(pr.joint_names))))
            except ValueError as exc:
                pr.problems.append(f"{name}: {topics.joint_states}: {' '.join(str(exc).split())}")
    for t, s in stamps.items():
        if len(s) >= 2:
            pr.rates_hz[t] = (len(s) - 1) / max((max(s) - min(s)) / 1e9, 1e-9)
        elif not s:
            pr.problems.append(f"{name}: {t} is empty")
    # sync: every colour / depth stream against the first camera's colour clock (header stamps)
    if found and all(ct.color and stamps.get(ct.color) for ct in found.values()):
        clock = np.array(sorted(stamps[found[sorted(found)[0]].color]), dtype=np.int64)
        for cname, ct in found.items():
            worst = 0.0
            for t in (ct.color, ct.depth):
                if t and stamps.get(t):
                    _, err = nearest_index(np.array(sorted(stamps[t]), dtype=np.int64), clock)
                    worst = max(worst, float(err.max()) / 1e6)
                    if err.max() > sync_tolerance_ms * 1e6:
                        pr.problems.append(f"{name}: {t}: not synchronised: {int((err > sync_tolerance_ms * 1e6).sum())} "
                                           f"frame(s) have no message within {sync_tolerance_ms:.0f} ms (worst {worst:.0f} ms)")
            pr.sync_ms[cname] = worst
    # TF connectivity of each camera (frame id of its camera_info)
    edges: dict[str, str] = {}
    for t in (topics.tf_static, topics.tf):
        for m in keep_small.get(t, []):
            for tr in m.transforms:
                tf_to_matrix(tr.transform)
                edges.setdefault(tr.child_frame_id, tr.header.frame_id)
    links = set(robot.link_names) if robot is not None else set()
    for cname, ct in found.items():
        infos = keep_small.get(ct.camera_info) if ct.camera_info else None
        if not infos:
            if ct.camera_info:
                pr.problems.append(f"{name}: {ct.camera_info} is empty")
            continue
        frame, seen = infos[0].header.frame_id, set()
        while frame != topics.world_frame and frame not in links and frame in edges and frame not in seen:
            seen.add(frame)
            frame = edges[frame]
        if frame == topics.world_frame:
            pr.tf_paths[cname] = topics.world_frame
        elif frame in links:
            pr.tf_paths[cname] = f"robot link {frame}"
        else:
            pr.tf_paths[cname] = f"none (ends at '{frame}')"
            pr.problems.append(f"{name}: {ct.camera_info}: camera '{cname}' (frame '{infos[0].header.frame_id}') has no TF "
                               f"path to '{topics.world_frame}' or a robot link in {topics.tf_static} / {topics.tf} "
                               f"(it ends at '{frame}')")
    return pr


def usable_episodes(refs: Sequence[EpisodeRef], robot, data_cfg, log: Callable[[str], None],
                    strict: Optional[bool] = None) -> list[EpisodeRef]:
    """The episodes whose bag passes :func:`probe_bag`; each bad one is logged in one line (its first
    problem) and skipped, or raised as a BagError when ``strict`` (default: ``data_cfg.strict``)."""
    strict = data_cfg.strict if strict is None else strict
    out = []
    for r in refs:
        pr = _probe_cached(r.bag, data_cfg.topics, robot, data_cfg.sync_tolerance_ms, data_cfg.cameras)
        if pr.ok:
            out.append(r)
            continue
        more = f" (+{len(pr.problems) - 1} more)" if len(pr.problems) > 1 else ""
        if strict:
            raise BagError(f"{pr.problems[0]}{more} [strict: a bad bag is fatal]")
        log(f"skipping bag {r.name}: {pr.problems[0]}{more}")
    return out


_PROBES: dict = {}


def _probe_cached(bag: Path, topics, robot, tol, cameras) -> BagProbe:
    try:
        st = max((f.stat().st_mtime_ns for f in Path(bag).iterdir()), default=0)
    except OSError:
        st = 0
    key = (str(Path(bag).resolve()), st, repr(topics), id(robot), tol, tuple(cameras or ()))
    if key not in _PROBES:
        _PROBES[key] = probe_bag(bag, topics, robot, tol, cameras)
    return _PROBES[key]
