"""Generate reference-world datasets: episodes as bags, a manifest, sidecars, contact sheets.

Output layout of ``generate_dataset(cfg, "rope", "tiny", out)``::

    out/manifest.json            {"object", "preset", "seed", "effects", "storage",
                                  "episodes": [{"name", "bag", "split", "task", "frames",
                                                "seconds_to_generate"}], "split_ratio", ...}
    out/rope_000/                rosbag2 directory (metadata.yaml + .db3 or .mcap)
    out/rope_000.meta.json       EVALUATION-ONLY sidecar (effects + magnitudes, object
                                 parameters, table height, task, seed, true wrist poses)
    out/rope_000.contact.png     contact sheet

Reproducibility: episode ``i`` of seed ``s`` draws everything (frame count,
object placement and shape, motion sizes) from ``SeedSequence([s, i])``;
tasks take turns over the episodes from a seed-dependent start; effects draw
nothing, so the same seed gives the same robot trajectory with any set of
effects.
"""

from __future__ import annotations

import contextlib
import json
import shutil
import time
from dataclasses import asdict
from pathlib import Path
from typing import Iterator, Optional, Sequence

import mujoco
import numpy as np
from tqdm import tqdm

from ..core.robot_frames import RobotFrames, robot_description
from .bag import OBJECT_POINTS_TOPIC, BagRecorder, topics_for
from .config import WorldConfig
from .contact_sheet import ContactSheet, sample_frames
from .effects import ActiveEffects, parse_effects
from .objects import make_object_geometry
from .planner import PlanError, make_plan
from .render import CameraRig
from .robot import ArmIK
from .scene import CAMERA_NAMES, build_scene, optical_frame_id
from .simulate import EpisodeSim
from .transforms import mat_to_quat

__all__ = ["generate_episode", "generate_dataset", "episode_name", "split_indices", "episode_stamp0_ns"]

MANIFEST = "manifest.json"


def episode_name(obj: str, index: int) -> str:
    return f"{obj}_{index:03d}"


def split_indices(n: int, ratio: float, seed: int) -> list[str]:
    """'train'/'test' per episode: a seeded shuffle, round(ratio * n) train, >= 1 test when n >= 2 and ratio < 1."""
    n_train = int(round(ratio * n))
    if n >= 2 and ratio < 1.0:
        n_train = min(n_train, n - 1)
    n_train = max(n_train, 1 if n >= 1 else 0)
    order = np.random.default_rng([int(seed), 0x5917]).permutation(n)
    split = ["test"] * n
    for i in order[:n_train]:
        split[int(i)] = "train"
    return split


def episode_stamp0_ns(cfg: WorldConfig, seed: int, index: int) -> int:
    """First header stamp of an episode: fixed epoch + seed offset + 10 min per episode."""
    return int((cfg.epoch_sec + (int(seed) % 100_000) * 1000 + index * 600) * 1_000_000_000)


@contextlib.contextmanager
def _collect_mujoco_warnings() -> Iterator[list[str]]:
    """Route MuJoCo's warnings into a list (instead of MUJOCO_LOG.TXT in the cwd) for the sidecar."""
    previous = mujoco.get_mju_user_warning()
    messages: list[str] = []
    mujoco.set_mju_user_warning(lambda msg: messages.append(str(msg).strip()))
    try:
        yield messages
    finally:
        mujoco.set_mju_user_warning(previous)


def _pose7(T: np.ndarray) -> list[float]:
    q = mat_to_quat(T[:3, :3])
    return [float(v) for v in (*T[:3, 3], *q)]


def generate_episode(
    cfg: WorldConfig,
    obj_name: str,
    preset: str,
    index: int,
    seed: int,
    effects: Sequence[str],
    out_dir: Path,
    storage: str = "sqlite3",
    task: Optional[str] = None,
    frames: Optional[int] = None,
    ik: Optional[ArmIK] = None,
    progress: bool = False,
) -> dict:
    """Simulate, render and record one episode; returns its manifest entry (without split)."""
    t_start = time.perf_counter()
    rc = cfg.robot_config
    assert rc is not None and cfg.effects is not None
    pre = cfg.preset(preset)
    obj = cfg.object(obj_name)
    name = episode_name(obj_name, index)
    out_dir = Path(out_dir)
    ss = np.random.SeedSequence([int(seed), int(index)])
    rng = np.random.default_rng(ss)
    n_frames = int(frames) if frames else int(rng.integers(pre.frames[0], pre.frames[1] + 1))
    allowed = cfg.tasks.get(obj_name, ["lift"])
    if task is None:
        # Tasks take turns over the episodes (balanced datasets), starting at a seed-dependent task.
        start = int(np.random.default_rng([int(seed), 0x7A5C]).integers(len(allowed)))
        task = allowed[(start + int(index)) % len(allowed)]
    elif task not in allowed:
        raise ValueError(f"task '{task}' is not configured for {obj_name} (allowed: {', '.join(allowed)})")
    if ik is None:
        ik = arm_ik(cfg)
    spf = cfg.steps_per_frame()
    table_z = cfg.table.height
    plan = geom = None
    errors = []
    for _attempt in range(10):
        geom = make_object_geometry(obj, rng, table_z)
        try:
            plan = make_plan(task, geom, obj, rc, ik, cfg.motion, rng, n_frames, cfg.fps, spf, table_z)
            break
        except PlanError as exc:
            errors.append(str(exc))
    if plan is None or geom is None:
        raise RuntimeError(f"{name}: no reachable plan after 10 placements ({errors[-1]})")

    with _collect_mujoco_warnings() as mj_warnings:
        eff = ActiveEffects(list(effects), cfg.effects)
        young, mass, table_mu = eff.young(obj), eff.mass(obj), eff.table_friction(cfg.table)
        scene = build_scene(cfg, obj, geom, pre.width, pre.height, young, mass, table_mu)
        # the effort noise has its own stream: switching it on or off moves no other draw
        effort_rng = np.random.default_rng(np.random.SeedSequence([int(seed), int(index), 0xEFF0]))
        sim = EpisodeSim(scene, plan, eff, spf, cfg.physics.max_element_stretch, effort_rng)
        sim.settle(cfg.physics.settle_seconds)

        stamp0 = episode_stamp0_ns(cfg, seed, index)
        period_ns = 1e9 / cfg.fps
        sheet = ContactSheet(CAMERA_NAMES, sample_frames(n_frames, cfg.contact_sheet.frames), cfg.contact_sheet.tile_width)
        wrist_poses: list[list[float]] = []
        final_points = None
        bag_dir = out_dir / name
        tf_static = [("world", rc.base_link, scene.base_T), (rc.wrist_camera.parent, optical_frame_id("cam_wrist"), scene.wrist_T)]
        tf_static += [("world", optical_frame_id(c), scene.camera_T[c]) for c in ("cam_front", "cam_side")]
        rig = CameraRig(scene, pre.width, pre.height)
        links = RobotFrames(rc.urdf_path())
        link_static = links.static_transforms()
        created = not bag_dir.exists()
        try:
            with BagRecorder(bag_dir, CAMERA_NAMES, storage) as bag:
                bar = tqdm(total=n_frames, desc=f"  {name}", unit="frame", leave=False, disable=not progress)
                for fs in sim.frames(n_frames):
                    stamp = stamp0 + int(round(fs.index * period_ns))
                    if fs.index == 0:
                        bag.write_tf_static(stamp, tf_static)
                        bag.write_robot_description(stamp, robot_description(rc.urdf_path()))
                    cams = rig.render_all(scene.data)
                    link_tf = link_static + [(p, c, T[0]) for p, c, T in
                                             links.moving_transforms(sim.joint_names, fs.position)]
                    bag.write_frame(stamp, sim.joint_names, fs.position, fs.velocity, fs.effort, cams, rig.K,
                                    fs.object_points, link_tf)
                    if sheet.wants(fs.index):
                        sheet.add(fs.index, cams)
                    wrist_poses.append(_pose7(fs.wrist_T))
                    final_points = fs.object_points
                    bar.update(1)
                bar.close()
        except BaseException:
            if created:  # never leave a half-written episode behind
                shutil.rmtree(bag_dir, ignore_errors=True)
            raise
        finally:
            rig.close()
    sheet.write(out_dir / f"{name}.contact.png", f"{name}  object={obj_name}  task={task}  seed={seed}  frames={n_frames}")
    seconds = time.perf_counter() - t_start

    g0 = geom.points
    sidecar = {
        "evaluation_only": True,
        "note": "Ground truth for evaluation. Training code must never read this file or /world/object_points.",
        "name": name,
        "object": obj_name,
        "preset": preset,
        "task": task,
        "seed": int(seed),
        "episode_index": int(index),
        "frames": n_frames,
        "fps": cfg.fps,
        "first_stamp_ns": stamp0,
        "effects": eff.magnitudes(),
        "effects_log": eff.log,
        "object_params": {
            "kind": obj.kind,
            "dim": geom.dim,
            "n_vertices": int(len(g0)),
            "n_elements": int(len(geom.elements)),
            "mass_kg": mass,
            "young_pa": young,
            "poisson": obj.poisson,
            "damping_s": obj.damping,
            "radius_m": obj.radius,
            "friction": obj.friction,
            "config": asdict(obj),
            "placement": {"center_xy": geom.center_xy.round(5).tolist(), "yaw_rad": round(geom.yaw, 6)},
            "rest_points_world": g0.round(6).tolist(),
        },
        "table": {
            "height_m": table_z,
            "plane_world": [0.0, 0.0, 1.0, -table_z],
            "friction": table_mu,
            "size_m": cfg.table.size,
            "center_xy": cfg.table.center_xy,
        },
        "robot": {
            "name": rc.name,
            "urdf": str(rc.urdf_path()),
            "base_link": rc.base_link,
            "hand_link": rc.hand_link,
            "world_T_base": _pose7(scene.base_T),
            "arm_control": "ideal position control (joints set to the plan every physics step)",
        },
        "cameras": {
            "K": rig.K.round(6).tolist(),
            "width": pre.width,
            "height": pre.height,
            "world_T_optical": {c: _pose7(scene.camera_T[c]) for c in ("cam_front", "cam_side")},
            "wrist_parent_T_optical": _pose7(scene.wrist_T),
            "pose_format": "x y z qw qx qy qz (parent <- child)",
        },
        "wrist_camera_world_poses": wrist_poses,
        "plan": plan.describe(),
        "grasp": sim.grasp_log,
        "mujoco_warnings": mj_warnings[:20],
        "final_object_centroid": None if final_points is None else np.asarray(final_points, float).mean(0).round(6).tolist(),
        "seconds_to_generate": round(seconds, 3),
    }
    with open(out_dir / f"{name}.meta.json", "w", encoding="utf-8") as fh:
        json.dump(sidecar, fh, indent=1)
    return {"name": name, "bag": name, "task": task, "frames": n_frames, "seconds_to_generate": round(seconds, 3)}


def arm_ik(cfg: WorldConfig) -> ArmIK:
    """The world's arm IK: its robot at ``robot_base_xyz``, turned ``robot_base_yaw_deg`` about z."""
    rc = cfg.robot_config
    assert rc is not None
    yaw = np.radians(cfg.robot_base_yaw_deg)
    return ArmIK(rc, np.asarray(cfg.robot_base_xyz, float), np.array([np.cos(yaw / 2), 0.0, 0.0, np.sin(yaw / 2)]))


_WORKER_IK: Optional[ArmIK] = None  # a dataset worker's arm IK, built once per process (_start_worker)


def _start_worker(cfg: WorldConfig) -> None:
    global _WORKER_IK
    _WORKER_IK = arm_ik(cfg)


def _worker_episode(*args, **kwargs) -> dict:
    """:func:`generate_episode` in a dataset worker, with the worker's arm IK."""
    return generate_episode(*args, ik=_WORKER_IK, **kwargs)


def _clear_outputs(out_dir: Path, names: list[str]) -> None:
    for n in names:
        p = out_dir / n
        if p.is_dir():
            shutil.rmtree(p)
        for suffix in (".meta.json", ".contact.png"):
            q = out_dir / f"{n}{suffix}"
            if q.exists():
                q.unlink()
    m = out_dir / MANIFEST
    if m.exists():
        m.unlink()


def generate_dataset(
    cfg: WorldConfig,
    obj_name: str,
    preset: str,
    out_dir: Path | str,
    episodes: Optional[int] = None,
    seed: int = 0,
    effects: Sequence[str] | str | None = None,
    storage: str = "sqlite3",
    task: Optional[str] = None,
    frames: Optional[int] = None,
    overwrite: bool = False,
    progress: bool = True,
    workers: int = 1,
) -> dict:
    """Generate ``episodes`` episodes (default: the preset's) into ``out_dir``; returns the manifest.

    ``workers``: episodes generated at once, each in its own process (every episode is seeded by
    ``(seed, index)`` alone, so the bags do not depend on it; the manifest lists them in order).
    """
    pre = cfg.preset(preset)
    cfg.object(obj_name)
    if task is not None and task not in cfg.tasks.get(obj_name, []):
        raise ValueError(f"task '{task}' is not configured for {obj_name} (allowed: {', '.join(cfg.tasks.get(obj_name, []))})")
    if storage not in ("sqlite3", "mcap"):
        raise ValueError(f"unknown storage '{storage}' (known: sqlite3, mcap)")
    eff_names = parse_effects(effects)
    n = int(episodes) if episodes is not None else pre.episodes
    if n < 1:
        raise ValueError("episodes must be >= 1")
    if workers < 1:
        raise ValueError(f"workers must be >= 1 (got {workers})")
    if frames is not None and frames < 8:
        raise ValueError(f"frames must be >= 8 (got {frames}): shorter episodes would move the arm implausibly fast")
    out_dir = Path(out_dir)
    names = [episode_name(obj_name, i) for i in range(n)]
    existing = [p for p in [out_dir / MANIFEST, *(out_dir / nm for nm in names)] if p.exists()]
    if existing and not overwrite:
        raise FileExistsError(f"output exists: {existing[0]} (use --overwrite to replace)")
    out_dir.mkdir(parents=True, exist_ok=True)
    if overwrite:
        _clear_outputs(out_dir, names)
    rc = cfg.robot_config
    assert rc is not None
    split = split_indices(n, pre.split_ratio, seed)
    manifest = {
        "object": obj_name,
        "preset": preset,
        "seed": int(seed),
        "effects": eff_names,
        "storage": storage,
        "split_ratio": pre.split_ratio,
        "episodes": [],
        "fps": cfg.fps,
        "width": pre.width,
        "height": pre.height,
        "cameras": list(CAMERA_NAMES),
        "topics": topics_for(CAMERA_NAMES),
        "evaluation_only_topics": [OBJECT_POINTS_TOPIC],
        "robot": rc.name,
        "generator": "soma world (MuJoCo reference world)",
    }
    bar = tqdm(total=n, desc=f"soma world {obj_name}/{preset}", unit="episode", disable=not progress)

    def add(entry: dict) -> None:
        entry["split"] = split[names.index(entry["name"])]
        manifest["episodes"].append(entry)
        manifest["episodes"].sort(key=lambda e: names.index(e["name"]))
        bar.update(1)
        bar.set_postfix(last=f"{entry['seconds_to_generate']:.1f}s", task=entry["task"])
        with open(out_dir / MANIFEST, "w", encoding="utf-8") as fh:  # written after every episode
            json.dump(manifest, fh, indent=1)

    common = dict(storage=storage, task=task, frames=frames)
    if workers == 1 or n == 1:
        ik = arm_ik(cfg)
        for i in range(n):
            add(generate_episode(cfg, obj_name, preset, i, seed, eff_names, out_dir, ik=ik, progress=progress,
                                 **common))
    else:
        import multiprocessing
        from concurrent.futures import ProcessPoolExecutor, as_completed

        # spawn: a fresh interpreter per worker (MuJoCo's GL context and torch threads do not survive a fork)
        with ProcessPoolExecutor(max_workers=min(workers, n), mp_context=multiprocessing.get_context("spawn"),
                                 initializer=_start_worker, initargs=(cfg,)) as pool:
            futures = [pool.submit(_worker_episode, cfg, obj_name, preset, i, seed, eff_names, out_dir, **common)
                       for i in range(n)]
            for fut in as_completed(futures):
                add(fut.result())
    bar.close()
    return manifest

