"""`make demo`: the main job of soma_ros on an embedded default, end to end.

1. Generate a small reference-world rope dataset (MuJoCo -> rosbags), or reuse it.
2. Train the `cpu` simulator briefly with `soma train` (resumable: a rerun reuses it).
3. Start `soma_sim_node` on the checkpoint and scene bundle, record its output
   with `soma_recorder`, and replay a held-out bag into it with
   `soma_bag_player`, exactly as a robot would drive it.
4. Evaluate the held-out episode open-loop (`soma eval`) and write a report:
   metrics, live rates and latency from /soma/status, and a side-by-side
   contact sheet of measured vs live-simulated images.

Everything lands in runs/demo/ (checkpoint.pt, scene/, data/, heldout_bag/,
live_bag/, report.md, contact_sheet.png). Every process that starts ROS runs
with LOCALHOST discovery and its own ROS_DOMAIN_ID.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np


def _log(msg: str) -> None:
    print(f"[demo] {msg}", flush=True)


def _run(cmd: list[str], env: dict, what: str) -> None:
    _log(f"{what}: {' '.join(cmd[2:] if cmd[:2] == [sys.executable, '-m'] else cmd)}")
    r = subprocess.run(cmd, env=env)
    if r.returncode != 0:
        raise SystemExit(f"[demo] {what} failed (exit {r.returncode})")


def _env() -> dict:
    from .nodes.testing import ros_env, unique_domain_id

    dom = int(os.environ.get("ROS_DOMAIN_ID") or unique_domain_id())
    return ros_env(dom, {"MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")})


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default="runs/demo")
    ap.add_argument("--object", default="rope")
    ap.add_argument("--episodes", type=int, default=8)
    ap.add_argument("--task", default="lift", help="reference-world task of every episode (lift, drag, fold, drop)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--train-config", default="config/train/tiny.yaml")
    ap.add_argument("--rate", type=float, default=1.0, help="bag replay rate factor")
    args = ap.parse_args(argv)
    t_start = time.time()
    out = Path(args.out).resolve()
    out.mkdir(parents=True, exist_ok=True)
    env = _env()
    py = [sys.executable, "-m"]

    # 1. reference-world data
    data = out / "data"
    if not (data / "manifest.json").is_file():
        _run(py + ["soma_ros.cli", "world", "--object", args.object, "--preset", "tiny", "--episodes",
                   str(args.episodes), "--seed", str(args.seed), "--task", args.task, "--out", str(data)], env,
             "reference world")
    else:
        _log(f"reusing dataset {data}")
    manifest = json.loads((data / "manifest.json").read_text())
    test_eps = [e for e in manifest["episodes"] if e["split"] == "test"]
    if not test_eps:
        raise SystemExit("[demo] the dataset has no held-out episode")
    held = test_eps[0]
    held_bag = out / "heldout_bag"
    if not held_bag.exists():
        shutil.copytree(data / held["bag"], held_bag)

    # 2. training (resumable; a finished run returns at once)
    _run(py + ["soma_ros.cli", "train", "--data", str(data), "--config", args.train_config, "--out", str(out)],
         env, "training")
    ckpt, scene = out / "checkpoint.pt", out / "scene"

    # 3. live: node + recorder + bag player. The node starts from the run's G_0; the
    #    held-out episode starts from G_0 aligned to its own first frame, which is sent
    #    through /soma/reset exactly as a user would (soma scene reset --file).
    from soma_ros.evaluation.evaluate import EvalContext

    from .core.ply import write_ply
    from .nodes.testing import RosProcess

    init_ply = out / "heldout_initial_scene.ply"
    write_ply(init_ply, EvalContext.from_run(out, data).store.initial_splats(held["name"]))

    live_bag = out / "live_bag"
    if live_bag.exists():
        shutil.rmtree(live_bag)
    from .core.scene_bundle import SceneBundle

    cams = [c.name for c in SceneBundle.load(scene).cameras]
    topics = ["/soma/status", "/soma/splats", "/joint_states"]
    for c in cams:
        topics += [f"/soma/{c}/image_raw", f"/soma/{c}/depth"]
    node = RosProcess("soma_ros.nodes.sim_node", ["--ros-args", "-p", f"checkpoint:={ckpt}", "-p", f"scene:={scene}",
                                                  "-p", "render_rate_hz:=10.0", "-p", "splat_rate_hz:=2.0"], env, "sim_node")
    rec = None
    try:
        rec = RosProcess("soma_ros.nodes.recorder", ["--out", str(live_bag), "--topics", *[
            t + (":soma_msgs/msg/SimStatus" if t.endswith("status") else
                 ":sensor_msgs/msg/PointCloud2" if t.endswith("splats") else
                 ":sensor_msgs/msg/JointState" if t == "/joint_states" else ":sensor_msgs/msg/Image") for t in topics]],
            env, "recorder")
        _run(py + ["soma_ros.cli", "scene", "reset", "--file", str(init_ply), "--timeout", "120"], env,
             "resetting the live node to the held-out episode's initial scene")
        _run(py + ["soma_ros.nodes.bag_player", str(held_bag), "--rate", str(args.rate), "--wait-for-subscribers", "2",
                   "--wait-timeout", "120"], env, "replaying the held-out bag into the live node")
        time.sleep(1.0)  # let the last images of the replay arrive
    finally:
        if rec is not None:
            rec.stop()
        node.stop()
    _log(f"live output recorded to {live_bag}")

    # 4. evaluation + report
    eval_dir = out / "eval"
    _run(py + ["soma_ros.cli", "eval", "--checkpoint", str(ckpt), "--data", str(data), "--split", "test",
               "--out", str(eval_dir)], env, "open-loop evaluation of the held-out episodes")
    from .data.bags import BagError
    from .demo_report import write_report

    try:
        report = write_report(out, held_bag, live_bag, eval_dir, cams, seconds=time.time() - t_start)
    except BagError as exc:
        raise SystemExit(f"[demo] report: {exc}") from None
    _log(f"report: {report}")
    _log(f"done in {time.time() - t_start:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
