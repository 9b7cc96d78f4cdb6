"""`soma resim`: open-loop resimulation of one recorded bag, without ROS running.

    soma resim --checkpoint RUN --bag BAG --out OUT [--scene DIR] [--cameras a,b] [--storage mcap|sqlite3]

The model is rolled out open loop under the bag's recorded /joint_states from the
same initial state ``soma eval`` uses for that episode (the run's G_0 aligned to the
bag's frame-0 object points; when BAG is an episode of the dataset the run was
trained on, exactly that episode, its name, split and cached initial state), and
scored by the evaluation harness (:mod:`soma_ros.evaluation.evaluate`): the metrics equal
``soma eval``'s for the same episode.

Writes into OUT:
  resim_bag/       rosbag2 (mcap by default: open resim_bag/resim_bag.mcap in Foxglove)
                   with every recorded topic copied through byte for byte, plus per
                   recorded frame, stamped with that frame's stamp (as soma_sim_node does):
                     <prefix>/<cam>/image_raw     sensor_msgs/Image rgb8, the recorded camera's size
                     <prefix>/<cam>/depth         sensor_msgs/Image 32FC1, metres (0 = no splat)
                     <prefix>/<cam>/camera_info   sensor_msgs/CameraInfo
                     <prefix>/splats              sensor_msgs/PointCloud2, soma_msgs/SplatLayout + packed rgb
                     /tf                          <world> -> <sim-frame> (identity),
                                                  <sim-frame> -> <sim-frame>/<cam>_optical
  metrics.json, table.md   the evaluation harness's report of this episode (masked
                   PSNR / SSIM / LPIPS, depth AbsRel / RMSE, Chamfer when the bag has
                   the ground-truth /world/object_points), plus a "resim" section
  sheets/<episode>.png     contact sheet: measured | simulated | |error| per camera

The cameras simulated and scored are the ones the bag has (found from its topics as
:func:`soma_ros.data.bags.discover_cameras` does: any names, nested namespaces, raw or
compressed colour), posed from the bag's own TF, so a bag from another camera set
than the training episodes works. Errors are one line: a missing or non-rosbag2
bag, a bag without /joint_states, joint names or robot that do not match the
checkpoint/scene, a camera without camera_info or TF path, an unknown camera, an
existing OUT/resim_bag (without --force).
"""

from __future__ import annotations

import argparse
import shutil
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator, Optional, Sequence

import numpy as np

from . import documented_parser

#: name of the output bag folder inside OUT (like `make demo`'s live_bag/)
BAG_DIR = "resim_bag"
#: the split name of a bag that is not an episode of the run's dataset
RESIM_SPLIT = "resim"


def register(subparsers) -> None:
    p = documented_parser(subparsers, "resim", "open-loop resimulation of one bag, without ROS running", __doc__)
    p.add_argument("--checkpoint", required=True, metavar="CKPT",
                   help="run folder, checkpoint.pt, spring_mass.pt (or its folder), or 'static' (with --run)")
    p.add_argument("--bag", required=True, metavar="BAG", help="recorded episode: a rosbag2 folder (sqlite3 or mcap)")
    p.add_argument("--out", required=True, metavar="OUT", help="output folder")
    p.add_argument("--run", default=None, metavar="RUN",
                   help="run folder giving the scene and the data settings (default: the checkpoint's folder)")
    p.add_argument("--scene", default=None, metavar="DIR", help="scene bundle to start from (default: RUN/scene)")
    p.add_argument("--cameras", default=None, metavar="A,B",
                   help="cameras to simulate into the bag (default: all; the metrics always use all)")
    p.add_argument("--storage", default="mcap", choices=["mcap", "sqlite3"], help="output bag storage (default: mcap)")
    p.add_argument("--prefix", default="/soma", help="prefix of the simulated topics (default: /soma)")
    p.add_argument("--sim-frame", default="soma_sim", metavar="FRAME",
                   help="TF frame of the simulated splats and cameras (default: soma_sim, as soma_sim_node)")
    p.add_argument("--name", default=None, help="variant name in the report (default: from the checkpoint)")
    p.add_argument("--device", default="cpu", choices=["cpu", "cuda", "auto"], help="rollout and render device")
    p.add_argument("--no-lpips", action="store_true", help="skip LPIPS (faster)")
    p.add_argument("--no-sheets", action="store_true", help="no contact sheet")
    p.add_argument("--force", action="store_true", help="replace an existing OUT/resim_bag")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


# --------------------------------------------------------------------------- the bag
@dataclass
class BagScan:
    """What resim needs to know about the input bag before reading it for real."""

    path: Path
    topics: dict[str, str]  # topic -> msgtype
    counts: dict[str, int]
    joint_names: list[str]
    camera_info: dict[str, tuple[np.ndarray, int, int]] = field(default_factory=dict)  # cam -> (K, width, height)


def resolve_bag(path: str | Path) -> Path:
    """The rosbag2 folder of ``path`` (a folder, or a storage file inside one)."""
    p = Path(path)
    if not p.exists():
        raise FileNotFoundError(f"bag not found: {p}")
    if p.is_file() and p.suffix in (".mcap", ".db3") and (p.parent / "metadata.yaml").is_file():
        p = p.parent
    if not p.is_dir() or not (p / "metadata.yaml").is_file():
        raise ValueError(f"{p}: not a rosbag2 folder (no metadata.yaml)")
    return p


def scan_bag(bag: Path, joint_states: str, camera_info_topics: dict[str, str]) -> BagScan:
    """Topics, the joint names of the first ``joint_states`` message and each camera's first CameraInfo."""
    from rosbags.highlevel import AnyReader
    from rosbags.interfaces import ConnectionExtRosbag2

    from soma_ros.bagtypes import typestore

    try:
        reader = AnyReader([bag], default_typestore=typestore())
        reader.open()
    except Exception as exc:  # rosbags raises its own error types for unreadable bags
        raise ValueError(f"{bag}: not a readable rosbag2 ({type(exc).__name__}: {exc})") from None
    try:
        if not all(isinstance(c.ext, ConnectionExtRosbag2) for c in reader.connections):
            raise ValueError(f"{bag}: not a rosbag2 bag")
        topics = {c.topic: c.msgtype for c in reader.connections}
        counts: dict[str, int] = {}
        for c in reader.connections:
            counts[c.topic] = counts.get(c.topic, 0) + int(c.msgcount)
        if joint_states not in topics:
            raise ValueError(f"{bag}: no {joint_states} topic: a resim follows the recorded joint states "
                             f"(topics: {', '.join(sorted(topics)) or 'none'})")
        if counts[joint_states] == 0:
            raise ValueError(f"{bag}: {joint_states} is empty")
        want = {joint_states} | {t for t in camera_info_topics.values() if t in topics}
        first: dict[str, object] = {}
        conns = [c for c in reader.connections if c.topic in want]
        for conn, _ts, raw in reader.messages(connections=conns):
            if conn.topic not in first:
                first[conn.topic] = reader.deserialize(raw, conn.msgtype)
                if len(first) == len(want):
                    break
    finally:
        reader.close()
    from soma_ros.core.cameras import k_from_camera_info

    infos = {}
    for cam, t in camera_info_topics.items():
        m = first.get(t)
        if m is not None:
            infos[cam] = (k_from_camera_info(m.k), int(m.width), int(m.height))  # the renderer's pixel centres
    return BagScan(bag, topics, counts, [str(n) for n in first[joint_states].name], infos)


def _episode_in_dataset(checkpoint_file: Optional[Path], bag: Path):
    """(dataset dir, EpisodeRef) when ``bag`` is an episode of the dataset the checkpoint was trained on
    (the same folder, not a copy), else None."""
    from soma_ros.core.checkpoint import read_checkpoint
    from soma_ros.data.dataset import load_dataset

    if checkpoint_file is None or not checkpoint_file.is_file():
        return None
    try:
        ds = read_checkpoint(checkpoint_file)["extra"].get("dataset")
    except ValueError:  # a spring-mass file or something else: no dataset recorded
        return None
    if not ds or not (Path(ds) / "manifest.json").is_file():
        return None
    try:
        refs = load_dataset(ds)
    except (FileNotFoundError, ValueError):
        return None
    target = bag.resolve()
    for r in refs:
        if Path(r.bag).resolve() == target:
            return Path(ds), r
    return None


def _one_episode_dataset(folder: Path, bag: Path, name: str, frames: Optional[int]) -> Path:
    """A dataset folder whose manifest lists only ``bag`` (split 'resim')."""
    import json

    folder.mkdir(parents=True, exist_ok=True)
    entry = {"name": name, "bag": str(bag.resolve()), "split": RESIM_SPLIT, "task": None, "frames": frames}
    (folder / "manifest.json").write_text(json.dumps({"episodes": [entry]}, indent=1))
    return folder


def _robot_name(config: str) -> str:
    return Path(str(config)).stem if str(config).endswith((".yaml", ".yml")) else str(config)


# --------------------------------------------------------------------------- the rollout
class _Tap:
    """A RolloutModel that records the frames another one yields (means, covs on the CPU)."""

    def __init__(self, model) -> None:
        self.model = model
        self.kind = getattr(model, "kind", "model")
        self.frames: list[tuple] = []

    def rollout(self, ep, init, scene) -> Iterator:
        self.frames = []
        for means, covs in self.model.rollout(ep, init, scene):
            self.frames.append((means.detach().float().cpu().clone(), covs.detach().float().cpu().clone()))
            yield means, covs

    def describe(self) -> dict:
        return self.model.describe()

    def to(self, device) -> "_Tap":
        self.model.to(device)
        return self


# --------------------------------------------------------------------------- simulated messages
def _transform(T: np.ndarray, parent: str, child: str, stamp):
    """[4, 4] parent <- child -> geometry_msgs/TransformStamped (as soma_sim_node publishes)."""
    from soma_ros.nodes.conversions import matrix_to_tf

    return matrix_to_tf(T, parent, child, stamp)


class SimFrames:
    """The simulated messages of each recorded frame, built with the live node's message builders
    (:mod:`soma_ros.nodes.conversions`, no rclpy) and converted to rosbags messages."""

    def __init__(self, ep, init, states: Sequence[tuple], cameras: Sequence[str],
                 intrinsics: dict[str, tuple[np.ndarray, int, int]], prefix: str, world_frame: str,
                 sim_frame: str, device: str = "cpu") -> None:
        import torch

        if len(states) != ep.num_frames:
            raise RuntimeError(f"resim: {len(states)} simulated frames for {ep.num_frames} recorded frames")
        self.ep, self.init, self.states = ep, init, states
        self.cameras = list(cameras)
        self.idx = [ep.camera_index(c) for c in self.cameras]
        sizes = {intrinsics[c][1:] for c in self.cameras}
        if len(sizes) != 1:
            raise ValueError(f"cameras {', '.join(self.cameras)} differ in image size; simulate them one size at a time")
        (self.width, self.height), = sizes
        self.K = np.stack([intrinsics[c][0] for c in self.cameras])
        self.prefix = prefix.rstrip("/")
        self.world_frame, self.sim_frame = world_frame, sim_frame
        self.device = torch.device(device)
        self.colors = init.colors().float().to(self.device)
        self.opacities = init.opacities.float().to(self.device)
        self.template = init.to(device="cpu")

    def topics(self) -> dict[str, str]:
        t = {f"{self.prefix}/splats": "sensor_msgs/msg/PointCloud2", "/tf": "tf2_msgs/msg/TFMessage"}
        for c in self.cameras:
            t[f"{self.prefix}/{c}/image_raw"] = "sensor_msgs/msg/Image"
            t[f"{self.prefix}/{c}/depth"] = "sensor_msgs/msg/Image"
            t[f"{self.prefix}/{c}/camera_info"] = "sensor_msgs/msg/CameraInfo"
        return t

    def stamp_ns(self, t: int) -> int:
        return int(self.ep.stamps_ns[t])

    def messages(self, t: int) -> list[tuple[str, object]]:
        """[(topic, rclpy message)] of frame t."""
        import torch
        from tf2_msgs.msg import TFMessage

        from soma_ros.core.cameras import Cameras
        from soma_ros.core.render import render
        from soma_ros.core.simulator import splats_from_covariances
        from soma_ros.nodes.conversions import camera_info, image_depth32, image_rgb8, splats_to_cloud, stamp_from_ns

        stamp = stamp_from_ns(self.stamp_ns(t))
        means, covs = self.states[t]
        c2w = self.ep.cam_to_world[t, self.idx].double().numpy()
        cams = Cameras.from_cam_to_world(self.K, c2w, self.width, self.height, self.cameras, device=self.device)
        with torch.no_grad():
            out = render(means.to(self.device), covs.to(self.device), self.colors, self.opacities, cams,
                         background=torch.zeros(3, device=self.device))
        rgb = out.rgb_u8().cpu().numpy()
        depth = out.depth.float().cpu().numpy()
        msgs: list[tuple[str, object]] = []
        tfs = [_transform(np.eye(4), self.world_frame, self.sim_frame, stamp)]
        for i, c in enumerate(self.cameras):
            frame = f"{self.sim_frame}/{c}_optical"
            msgs.append((f"{self.prefix}/{c}/image_raw", image_rgb8(rgb[i], frame, stamp)))
            msgs.append((f"{self.prefix}/{c}/depth", image_depth32(depth[i], frame, stamp)))
            msgs.append((f"{self.prefix}/{c}/camera_info", camera_info(self.K[i], self.width, self.height, frame, stamp)))
            tfs.append(_transform(c2w[i], self.sim_frame, frame, stamp))
        msgs.append(("/tf", TFMessage(transforms=tfs)))
        # the splats of this frame (colours, opacities, mass from the initial splats), as the live
        # node publishes them
        splats = splats_from_covariances(means, covs, self.template)
        msgs.append((f"{self.prefix}/splats", splats_to_cloud(splats, self.sim_frame, stamp)))
        return msgs


def write_resim_bag(src: Path, dst: Path, sim: SimFrames, storage: str = "mcap", progress: bool = True) -> dict[str, int]:
    """Copy every message of ``src`` unchanged into a new bag ``dst`` and add ``sim``'s messages,
    in time order (a frame's simulated messages go before the recorded ones of the same time).
    Returns {topic: messages written}."""
    from rosbags.highlevel import AnyReader
    from rosbags.rosbag2 import StoragePlugin, Writer

    from soma_ros.bagtypes import typestore
    from soma_ros.nodes.rosbags_bridge import to_rosbags

    store = typestore()
    plugin = {"mcap": StoragePlugin.MCAP, "sqlite3": StoragePlugin.SQLITE3}[storage]
    counts: dict[str, int] = {}
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=sim.ep.num_frames, desc="soma resim bag", unit="frame", dynamic_ncols=True)
    try:
        with AnyReader([src], default_typestore=store) as reader, \
                Writer(dst, version=9, storage_plugin=plugin) as writer:
            out_conn = {}
            by_topic = {}
            for c in reader.connections:
                ext = c.ext
                if c.msgdef.data and c.digest:
                    oc = writer.add_connection(c.topic, c.msgtype, msgdef=c.msgdef.data, rihs01=c.digest,
                                               serialization_format=ext.serialization_format,
                                               offered_qos_profiles=ext.offered_qos_profiles)
                else:  # an older bag without embedded definitions: the typestore's
                    oc = writer.add_connection(c.topic, c.msgtype, typestore=store,
                                               serialization_format=ext.serialization_format,
                                               offered_qos_profiles=ext.offered_qos_profiles)
                out_conn[c.id] = oc
                by_topic.setdefault(c.topic, oc)
            sim_conn = {}
            for topic, msgtype in sim.topics().items():
                if topic in by_topic and by_topic[topic].msgtype == msgtype and topic == "/tf":
                    sim_conn[topic] = by_topic[topic]  # the recorded /tf carries the simulated transforms too
                else:
                    sim_conn[topic] = writer.add_connection(topic, msgtype, typestore=store)

            def put(conn, ts: int, raw: bytes) -> None:
                writer.write(conn, ts, raw)
                counts[conn.topic] = counts.get(conn.topic, 0) + 1

            T = sim.ep.num_frames
            t = 0

            def flush(until_ns: Optional[int]) -> None:
                nonlocal t
                while t < T and (until_ns is None or sim.stamp_ns(t) <= until_ns):
                    ts = sim.stamp_ns(t)
                    for topic, msg in sim.messages(t):
                        conn = sim_conn[topic]
                        put(conn, ts, store.serialize_cdr(to_rosbags(msg, store), conn.msgtype))
                    t += 1
                    if bar is not None:
                        bar.update(1)

            for conn, ts, raw in reader.messages():
                flush(ts)
                put(out_conn[conn.id], ts, raw)
            flush(None)
    except BaseException:
        shutil.rmtree(dst, ignore_errors=True)
        raise
    finally:
        if bar is not None:
            bar.close()
    return counts


# --------------------------------------------------------------------------- the command
def resimulate(checkpoint: str, bag: str | Path, out: str | Path, *, run_dir: Optional[str | Path] = None,
               scene: Optional[str | Path] = None, cameras: Optional[Sequence[str]] = None, storage: str = "mcap",
               prefix: str = "/soma", sim_frame: str = "soma_sim", name: Optional[str] = None,
               with_lpips: bool = True, contact_sheet: bool = True, device: str = "cpu", progress: bool = True,
               force: bool = False) -> dict:
    """Resimulate one bag (module docstring); returns the metrics dict written to OUT/metrics.json."""
    import torch

    from soma_ros.evaluation.baselines import StaticModel, load_model
    from soma_ros.training.config import load_train_config
    from soma_ros.evaluation.evaluate import EvalConfig, EvalContext, evaluate_models, write_model_report
    from soma_ros.core.scoring import EvalMetricsConfig

    from .eval import _run_dir

    t0 = time.time()
    if storage not in ("mcap", "sqlite3"):
        raise ValueError(f"unknown storage '{storage}' (mcap or sqlite3)")
    if not prefix.startswith("/") or prefix.rstrip("/") == "":
        raise ValueError(f"--prefix must be an absolute topic namespace such as /soma, got '{prefix}'")
    bag = resolve_bag(bag)
    out = Path(out)
    dst = out / BAG_DIR
    if dst.exists() and not force:
        raise ValueError(f"{dst} already exists (use --force to replace it)")
    if out.resolve() == bag.resolve() or bag.resolve() in out.resolve().parents:
        raise ValueError(f"--out {out} is inside the input bag {bag}")
    run = _run_dir(checkpoint, None if run_dir is None else str(run_dir))
    cfg_path = run / "train_config.yaml"
    if not cfg_path.is_file():
        raise FileNotFoundError(f"{run}: no train_config.yaml (is it a `soma train` run folder?)")
    topics = load_train_config(cfg_path).data.topics

    # ---- what the bag has (fast: no image is decoded)
    from soma_ros.core.scene_bundle import SceneBundle

    scene_dir = Path(scene) if scene is not None else run / "scene"
    if not (scene_dir / "scene.json").is_file():
        raise FileNotFoundError(f"scene bundle not found: {scene_dir}")
    bundle = SceneBundle.load(scene_dir)
    # the cameras the bag has (any names, flat or nested namespaces), not the training rig's
    from soma_ros.data.bags import discover_cameras

    scan = scan_bag(bag, topics.joint_states, {})
    bag_cams = discover_cameras(scan.topics, topics)
    info_topics = {c: ct.camera_info for c, ct in bag_cams.items() if ct.camera_info}
    scan = scan_bag(bag, topics.joint_states, info_topics)
    known = sorted(bag_cams)
    if not known:
        raise ValueError(f"{bag}: no camera topics matching {topics.color} (raw or {topics.compressed_suffix})")
    wanted = list(cameras) if cameras else list(known)
    unknown = [c for c in wanted if c not in known]
    if unknown:
        raise ValueError(f"unknown camera(s) {', '.join(unknown)}; the bag has {', '.join(known)}")
    no_info = [c for c in wanted if c not in scan.camera_info]
    if no_info:
        c = no_info[0]
        raise ValueError(f"{bag}: no {topics.topic('camera_info', bag_cams[c].namespace)} or "
                         f"{topics.topic('depth_camera_info', bag_cams[c].namespace)} for camera '{c}'")
    sim_topics = [t for t in scan.topics if t.startswith(prefix.rstrip("/") + "/")]
    if sim_topics:
        raise ValueError(f"{bag}: already has topics under {prefix} ({sim_topics[0]}, ...); choose another --prefix")

    # ---- the episode: one of the run's dataset (exactly soma eval's) or this bag alone
    ckpt_file = None
    if checkpoint != "static":
        p = Path(checkpoint)
        ckpt_file = p / "checkpoint.pt" if p.is_dir() else p
    found = _episode_in_dataset(run / "checkpoint.pt", bag)  # the run's dataset, as EvalContext.from_run
    model = StaticModel() if checkpoint == "static" else load_model(checkpoint)
    variant = name or ("static" if checkpoint == "static" else Path(checkpoint).resolve().name.replace(".pt", ""))
    with tempfile.TemporaryDirectory(prefix="soma_resim_") as tmp:
        if found is not None:
            data_dir, ref = found
            ctx = EvalContext.from_run(run, data_dir, scene)
            ctx.refs = [r for r in ctx.refs if r.name == ref.name]
            split = ref.split
        else:
            ep_name = bag.name
            if ep_name == bundle.extra.get("source_episode"):  # not that episode: never start from the unaligned G_0
                ep_name += "_resim"
            frames = scan.counts.get(bag_cams[wanted[0]].color or "")
            ctx = EvalContext.from_run(run, _one_episode_dataset(Path(tmp) / "data", bag, ep_name, frames), scene)
            split = RESIM_SPLIT

        # ---- checkpoint, scene and bag agree on the robot
        if ckpt_file is not None and ckpt_file.is_file() and checkpoint != "static":
            try:
                from soma_ros.core.checkpoint import read_checkpoint

                ck_robot = read_checkpoint(ckpt_file)["extra"].get("robot")
            except ValueError:
                ck_robot = None
            if ck_robot and _robot_name(ck_robot) != _robot_name(ctx.bundle.robot_config):
                raise ValueError(f"checkpoint {ckpt_file} was trained for robot '{ck_robot}' but scene "
                                 f"{ctx.scene_dir} is for robot '{ctx.bundle.robot_config}'")
        robot = ctx.store.robot
        zeros = np.zeros((1, len(scan.joint_names)))
        try:
            robot.q_from_joint_state(scan.joint_names, zeros)
            if robot.gripper_joint_names:
                robot.gripper_values(scan.joint_names, zeros)
        except ValueError as exc:
            raise ValueError(f"{bag}: {topics.joint_states} does not fit the robot '{robot.config.name}' of the "
                             f"checkpoint/scene: {exc}") from None
        if not ctx.refs:  # the bag did not pass the checks of soma_ros.data.sources.probe_bag
            raise ValueError(ctx.skipped[0] if ctx.skipped else f"{bag}: not usable")
        ref = ctx.refs[0]

        if dst.exists():
            shutil.rmtree(dst)
        out.mkdir(parents=True, exist_ok=True)

        # ---- rollout + the evaluation harness's scores (and contact sheet)
        tap = _Tap(model)
        ecfg = EvalConfig(metrics=EvalMetricsConfig(with_lpips=with_lpips), contact_sheets=contact_sheet,
                          progress=progress, device=device)
        res = evaluate_models({variant: tap}, ctx, split, {variant: out}, ecfg, log=lambda s: None)[variant]

        # ---- the output bag
        ep = ctx.store.episode(ref.name)
        init = ctx.store.initial_splats(ref.name)
        dev = "cuda" if device == "cuda" or (device == "auto" and torch.cuda.is_available()) else "cpu"
        sim = SimFrames(ep, init, tap.frames, wanted, scan.camera_info, prefix, topics.world_frame, sim_frame, dev)
        counts = write_resim_bag(bag, dst, sim, storage, progress)

    res["dataset"] = str(found[0]) if found is not None else str(bag)
    res["resim"] = {
        "bag": str(bag), "episode": ref.name, "split": split, "output_bag": str(dst), "storage": storage,
        "frames": ep.num_frames, "cameras": wanted, "stamps_ns": [int(s) for s in ep.stamps_ns.tolist()],
        "simulated_topics": {t: counts.get(t, 0) for t in sim.topics()},
        "recorded_topics": dict(scan.counts), "world_frame": topics.world_frame, "sim_frame": sim_frame,
        "seconds": round(time.time() - t0, 1),
    }
    write_model_report(out, res)
    return res


def run(args: argparse.Namespace) -> int:
    import sys

    import torch

    torch.set_num_threads(1)
    from soma_ros.evaluation.evaluate import format_metric
    from soma_ros.core.scoring import METRICS

    cams = [c.strip() for c in args.cameras.split(",") if c.strip()] if args.cameras else None
    if args.cameras is not None and not cams:
        raise ValueError("--cameras needs at least one camera name")
    t0 = time.time()
    res = resimulate(args.checkpoint, args.bag, args.out, run_dir=args.run, scene=args.scene, cameras=cams,
                     storage=args.storage, prefix=args.prefix, sim_frame=args.sim_frame, name=args.name,
                     with_lpips=not args.no_lpips, contact_sheet=not args.no_sheets, device=args.device,
                     progress=not args.quiet)
    r = res["resim"]
    ep = res["episodes"][r["episode"]]
    print(f"soma resim: {res['variant']} on {r['bag']} ({r['frames']} frames, episode {r['episode']}, "
          f"{time.time() - t0:.1f} s)")
    print("  " + "  ".join(f"{m}={format_metric(m, ep.get(m))}" for m in METRICS
                           if not (m == "lpips" and args.no_lpips)))
    for n in res.get("notes", []):
        print(f"  note: {n}", file=sys.stderr)
    out = Path(args.out)
    n_sim = sum(r["simulated_topics"].values())
    print(f"  wrote {r['output_bag']} ({len(r['recorded_topics'])} recorded topics copied, {n_sim} simulated "
          f"messages on {len(r['simulated_topics'])} topics), {out / 'metrics.json'}, {out / 'table.md'}"
          + ("" if args.no_sheets else f", {out / 'sheets'}/"))
    return 0
