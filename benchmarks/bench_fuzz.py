"""Fuzz benchmark of soma_sim_node: bad resets, a /joint_states flood, signals.

    python -m benchmarks.bench_fuzz [--splats 13000] [--flood-s 30] [--flood-hz 1000] [--json OUT.json]

Starts the node (an untrained ``cpu`` model on a generated rope, one 320x240
camera, ``rate_hz`` 30, ``render_rate_hz`` 10) as its own process on its own
ROS_DOMAIN_ID with LOCALHOST discovery, and plays an attacker or a careless client:

``resets``   every bad-input class the node must refuse (lying PLY headers,
             2,000,000 points inline, 1 GB files, wrong datatypes, overlapping
             fields, huge splats, a text file named .splat, paths outside
             ``scene_dirs``, a symlink to /etc/passwd, ...), one reset each while
             this process keeps publishing /joint_states at 100 Hz. For each: the
             answer time, the node's RSS before / peak (sampled every 10 ms) / after,
             the steps taken and joint states received while it was answered, and
             the reply. A valid reset and a second reset during a long one ("busy")
             are the controls.
``flood``    ``--flood-hz`` /joint_states for ``--flood-s`` seconds: the step rate
             and the image rate against their targets and against the same node's
             rates with ordinary (100 Hz) input just before; received / dropped /
             rejected counters; RSS before / peak / after.
``signals``  time from SIGTERM (or SIGINT) to exit with a reset running, during a
             flood, and idle; /dev/shm entries the node left behind.

The machine (CPU, cores, load before and after) is printed with the table; the
cores may be shared with other work, which the rates then show.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import signal
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Callable, Optional, Sequence

import numpy as np

from benchmarks.bench_live import LiveProbe, Poser, load_line, machine_line, rss_mb

TABLE_Z = 0.75


class RssSampler:
    """Peak RSS of a process, sampled every ``period`` s in a thread while in the ``with`` block."""

    def __init__(self, pid: int, period: float = 0.01) -> None:
        self.pid, self.period = pid, period
        self.peak = 0.0
        self._stop = threading.Event()

    def __enter__(self) -> "RssSampler":
        self.peak = rss_mb(self.pid)
        self._t = threading.Thread(target=self._run, daemon=True)
        self._t.start()
        return self

    def _run(self) -> None:
        while not self._stop.wait(self.period):
            try:
                self.peak = max(self.peak, rss_mb(self.pid))
            except Exception:  # noqa: BLE001 - the process ended
                return

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._t.join()


class Node:
    """One node process with a probe in this process's own rclpy context."""

    def __init__(self, run, params: Sequence[str], names: Sequence[str], cameras=("cam_front",)) -> None:
        import rclpy
        from rclpy.context import Context

        from soma_ros.nodes.testing import RosProcess, ros_env, unique_domain_id

        self.domain = unique_domain_id()
        os.environ["ROS_DOMAIN_ID"] = str(self.domain)
        self.ctx = Context()
        rclpy.init(args=[], context=self.ctx, domain_id=self.domain)
        args = ["--ros-args", "-p", f"checkpoint:={run[0]}", "-p", f"scene:={run[1]}"]
        for p in params:
            args += ["-p", p]
        self.proc = RosProcess("soma_ros.nodes.sim_node", args, ros_env(self.domain), name="fuzz_sim_node")
        self.probe = LiveProbe(self.ctx, names, cameras=cameras, splats=False)

    def started(self, vec, timeout: float = 600.0) -> None:
        p = self.probe
        ok = p.hold(vec, lambda: (p.last_status() is not None and p.count.get(("image", "cam_front"), 0) > 0)
                    or not self.proc.alive(), timeout)
        if not (ok and self.proc.alive()):
            raise RuntimeError(f"soma_sim_node did not start:\n{self.proc.output()[-4000:]}")
        # the shared-memory files the node has mapped (its DDS segments and lock files)
        self.shm = {ln.split()[-1] for ln in open(f"/proc/{self.proc.proc.pid}/maps") if "/dev/shm/" in ln}

    def stop_by_signal(self, sig: int, during: Optional[Callable[[], None]] = None) -> float:
        """Send ``sig`` (while ``during`` runs in a thread, if given); seconds until the process exits."""
        t0 = time.monotonic()
        os.killpg(self.proc.proc.pid, sig)
        while self.proc.proc.poll() is None and time.monotonic() - t0 < 30:
            if during is not None:
                during()
            else:
                time.sleep(0.005)
        return time.monotonic() - t0

    def close(self) -> dict:
        import rclpy

        self.proc.stop()
        self.probe.close()
        if self.ctx.ok():
            rclpy.shutdown(context=self.ctx)
        left = sorted(m for m in getattr(self, "shm", ()) if os.path.exists(m)
                      and not Path(m).name.startswith("lttng-ust-wait-"))  # LTTng's per-user files stay by design
        return {"rc": self.proc.proc.returncode, "shm_left": left, "output": self.proc.output()}


# --------------------------------------------------------------------------- the bad inputs
def _cloud(splats):
    from soma_ros.nodes.conversions import splats_to_cloud

    return splats_to_cloud(splats, "soma_sim")


def _variant(base, **kw):
    from soma_ros.nodes.testing import cloud_variant

    return cloud_variant(base, **kw)


def bad_inputs(allowed: Path, outside: Path) -> list[tuple[str, dict]]:
    """(name, ResetScene request fields) for every bad-input class, files written under the folders."""
    from sensor_msgs.msg import PointField

    from soma_ros.core.ply import write_ply
    from soma_ros.core.scenes import synthetic_rope

    rope = synthetic_rope(800, center=(0.45, 0.05, TABLE_Z), seed=5)
    base = _cloud(rope)
    cases: list[tuple[str, dict]] = []
    head = "ply\nformat ascii 1.0\nelement vertex 100000000\nproperty float x\nproperty float y\nproperty float z\nend_header\n"
    (allowed / "lying_1e8.ply").write_text(head + "0 0 0\n" * ((385 - len(head)) // 6))
    cases.append(("lying ASCII header 1e8 (385 B)", {"ply_path": str(allowed / "lying_1e8.ply")}))
    (allowed / "lying_1e12.ply").write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 1000000000000\n"
                                             b"property float x\nproperty float y\nproperty float z\nend_header\n" + bytes(24))
    cases.append(("lying binary header 1e12", {"ply_path": str(allowed / "lying_1e12.ply")}))
    names = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1",
             "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    hdr = ("ply\nformat binary_little_endian 1.0\nelement vertex 2000000\n"
           + "".join(f"property float {n}\n" for n in names) + "end_header\n").encode()
    with open(allowed / "valid_2M.ply", "wb") as f:  # a consistent 2M-splat file (136 MB, sparse)
        f.write(hdr)
        f.truncate(len(hdr) + 2_000_000 * 4 * len(names))
    cases.append(("valid 2M-splat PLY (136 MB)", {"ply_path": str(allowed / "valid_2M.ply")}))
    for name in ("huge_1GB.splat", "huge_1GB.ply"):
        with open(allowed / name, "wb") as f:
            f.truncate(2**30)
        cases.append((f"1 GB file {name.split('.')[-1]}", {"ply_path": str(allowed / name)}))
    n = 2_000_000
    xyz = np.zeros((n, 16), np.float32)
    xyz[:, 0] = np.linspace(0.3, 0.7, n)
    xyz[:, 2] = TABLE_Z
    cases.append(("2M points inline, splat layout (128 MB)", {"splats": _variant(base, width=n, row_step=64 * n,
                                                                                  data=xyz.tobytes())}))
    del xyz
    small = np.zeros((n, 3), np.float32)
    cases.append(("2M points inline, xyz only (24 MB)", {"splats": type(base)(
        height=1, width=n, point_step=12, row_step=12 * n, is_dense=True, data=small.tobytes(),
        fields=[PointField(name=k, offset=4 * i, datatype=7, count=1) for i, k in enumerate("xyz")])}))
    for dt, tn in ((2, "uint8"), (5, "int32")):
        cases.append((f"fields declared {tn}", {"splats": _variant(base, fields=[
            type(f)(name=f.name, offset=f.offset, datatype=dt, count=1) for f in base.fields])}))
    cases.append(("all fields at offset 0", {"splats": _variant(base, fields=[
        type(f)(name=f.name, offset=0, datatype=f.datatype, count=1) for f in base.fields])}))
    f3 = list(base.fields)
    f3[0] = type(f3[0])(name="x", offset=0, datatype=7, count=3)
    cases.append(("field count=3", {"splats": _variant(base, fields=f3)}))
    cases.append(("0 points", {"splats": _variant(base, width=0, data=b"")}))
    for sc in (0.1, 0.3):
        s = synthetic_rope(800, center=(0.45, 0.05, TABLE_Z), seed=5)
        s.scales = s.scales * 0 + sc
        cases.append((f"splat scales {sc} m", {"splats": _cloud(s)}))
    (allowed / "notes.splat").write_bytes((b"API_KEY=do-not-echo-this-line-0123456789abcdef\n" * 40)[:39 * 32])
    cases.append(("text file named .splat", {"ply_path": str(allowed / "notes.splat")}))
    write_ply(outside / "rope.ply", rope)
    cases.append(("valid file outside scene_dirs", {"ply_path": str(outside / "rope.ply")}))
    if not (allowed / "escape.ply").exists():
        (allowed / "escape.ply").symlink_to("/etc/passwd")
    cases.append(("symlink to /etc/passwd", {"ply_path": str(allowed / "escape.ply")}))
    cases.append(("/etc/passwd", {"ply_path": "/etc/passwd"}))
    cases.append(("/etc/splats.ply (missing)", {"ply_path": "/etc/splats.ply"}))
    cases.append(("relative path", {"ply_path": "rope.ply"}))
    return cases


def timed_reset(node: Node, vec, fields: dict, timeout: float = 120.0) -> dict:
    """One reset while publishing ``vec`` at 100 Hz: answer time, RSS, steps and inputs meanwhile."""
    from soma_msgs.srv import ResetScene

    p = node.probe
    req = ResetScene.Request()
    if "splats" in fields:
        req.splats = fields["splats"]
    req.ply_path = fields.get("ply_path", "")
    p.hold(vec, lambda: False, 0.5, hz=100.0)
    st0 = p.last_status()
    pid = node.proc.proc.pid
    rss0 = rss_mb(pid)
    with RssSampler(pid) as rs:
        t0 = time.monotonic()
        fut = p.reset_client.call_async(req)
        p.hold(vec, fut.done, timeout, hz=100.0)
        dt = time.monotonic() - t0
        st1 = p.last_status()
        p.hold(vec, lambda: False, 0.5, hz=100.0)
    resp = fut.result() if fut.done() else None
    return {"seconds": dt, "rss_before_mb": rss0, "rss_peak_mb": rs.peak, "rss_after_mb": rss_mb(pid),
            "steps_meanwhile": int(st1.step) - int(st0.step) if st1.num_splats == st0.num_splats else None,
            "joint_states_meanwhile": int(st1.joint_states_received) - int(st0.joint_states_received),
            "success": bool(resp.success) if resp else None, "message": resp.message if resp else "no answer"}


def flood(node: Node, vec, seconds: float, hz: float) -> dict:
    """Rates with 100 Hz input (``seconds`` / 3), then under a ``hz`` flood for ``seconds``."""
    p = node.probe
    pid = node.proc.proc.pid

    def window(s: float, rate: float, sample_rss: list) -> dict:
        names = list(p.names) + list(p.extra)
        good = list(vec) + [vec[p.names.index("panda_finger_joint1")]] * len(p.extra)
        st0 = p.last_status()
        img0 = p.count.get(("image", "cam_front"), 0)
        t0 = time.monotonic()
        sent, next_rss = 0, t0 + 1.0
        while (now := time.monotonic()) < t0 + s:
            due = int((now - t0) * rate) + 1
            while sent < due:
                p.publish(names=names, positions=good)
                sent += 1
            p.executor.spin_once(timeout_sec=0 if rate > 200 else 0.002)
            if now >= next_rss:
                sample_rss.append(rss_mb(pid))
                next_rss += 1.0
        t1 = time.monotonic()
        st1 = p.last_status()
        return {"seconds": t1 - t0, "sent": sent, "steps_per_s": (int(st1.step) - int(st0.step)) / (t1 - t0),
                "images_per_s": (p.count.get(("image", "cam_front"), 0) - img0) / (t1 - t0),
                "received": int(st1.joint_states_received) - int(st0.joint_states_received),
                "dropped": int(st1.joint_states_dropped) - int(st0.joint_states_dropped),
                "rejected": int(st1.joint_states_rejected) - int(st0.joint_states_rejected)}

    base_rss: list = []
    base = window(max(5.0, seconds / 3), 100.0, base_rss)
    rss0 = rss_mb(pid)
    samples = [rss0]
    fl = window(seconds, hz, samples)
    p.hold(vec, lambda: False, 2.0)
    return {"baseline": base, "flood": fl, "rss_before_mb": rss0, "rss_peak_mb": max(samples), "rss_after_mb": rss_mb(pid)}


# --------------------------------------------------------------------------- main
def main(argv: Optional[Sequence[str]] = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--splats", type=int, default=13000)
    ap.add_argument("--flood-s", type=float, default=30.0)
    ap.add_argument("--flood-hz", type=float, default=1000.0)
    ap.add_argument("--rate-hz", type=float, default=30.0)
    ap.add_argument("--render-rate-hz", type=float, default=10.0)
    ap.add_argument("--only", nargs="+", default=["resets", "flood", "signals"], choices=["resets", "flood", "signals"])
    ap.add_argument("--json", help="write the results here")
    args = ap.parse_args(argv)
    os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    from soma_ros.core.scenes import write_untrained_run
    from soma_ros.live import load_live

    say = lambda *a: print(*a, flush=True)  # noqa: E731
    work = Path(tempfile.mkdtemp(prefix="soma_fuzz_"))
    load0 = load_line()
    say(f"machine: {machine_line(1)}\n{load0} (before)")
    run = write_untrained_run(work / "run", n=args.splats, width=320, height=240)
    live = load_live(str(run[0]), str(run[1]))
    poser = Poser(live.robot, live.base_to_sim.matrix(), live.required_joints, live.bundle.gravity)
    hover = poser.solve((0.5, 0.02, TABLE_Z + 0.25))
    allowed, outside = work / "allowed", work / "outside"
    allowed.mkdir()
    outside.mkdir()
    params = [f"rate_hz:={args.rate_hz}", f"render_rate_hz:={args.render_rate_hz}", "splat_rate_hz:=0.0",
              "cameras:=[cam_front]", f"scene_dirs:=['{run[1]}', '{allowed}']"]
    res: dict = {"machine": machine_line(1), "load_before": load0, "splats": args.splats}

    node = Node(run, params, live.required_joints)
    try:
        node.started(hover)
        if "resets" in args.only:
            res["resets"] = []
            for name, fields in bad_inputs(allowed, outside):
                r = timed_reset(node, hover, fields)
                r["case"] = name
                res["resets"].append(r)
                say(f"  {name}: {r['seconds']:.3f} s, RSS {r['rss_before_mb']:.0f}/{r['rss_peak_mb']:.0f}/"
                    f"{r['rss_after_mb']:.0f} MB: {r['message']}")
            from soma_ros.core.scenes import synthetic_rope

            r = timed_reset(node, hover, {"splats": _cloud(synthetic_rope(args.splats, center=(0.5, 0.0, TABLE_Z)))})
            r["case"] = f"control: valid {args.splats}-splat cloud"
            res["resets"].append(r)
            say(f"  {r['case']}: {r['seconds']:.3f} s: {r['message']}")
        if "flood" in args.only:
            say(f"flood: {args.flood_hz:.0f} Hz for {args.flood_s:.0f} s after {max(5.0, args.flood_s / 3):.0f} s at 100 Hz")
            res["flood"] = flood(node, hover, args.flood_s, args.flood_hz)
            say(json.dumps(res["flood"]))
        if "signals" in args.only:
            from soma_msgs.srv import ResetScene

            from soma_ros.core.scenes import synthetic_rope

            req = ResetScene.Request()
            req.splats = _cloud(synthetic_rope(150_000, center=(0.5, 0.0, TABLE_Z)))
            first = node.probe.reset_client.call_async(req)
            node.probe.spin_for(0.3)
            second = node.probe.reset_client.call_async(ResetScene.Request(ply_path=str(run[1])))
            node.probe.spin_until(second.done, 30)
            res["busy_answer"] = second.result().message if second.done() else "no answer"
            res["first_done_at_sigterm"] = first.done()
            res["sigterm_during_reset_s"] = node.stop_by_signal(signal.SIGTERM)
    finally:
        end = node.close()
    res["rc_main"], res["shm_left_main"] = end["rc"], end["shm_left"]
    if "signals" in args.only:
        for label, sig, flooding in (("sigterm_during_flood_s", signal.SIGTERM, True),
                                     ("sigint_idle_s", signal.SIGINT, False)):
            n2 = Node(run, params, live.required_joints)
            try:
                n2.started(hover)
                during = None
                if flooding:
                    p = n2.probe
                    names = list(p.names) + list(p.extra)
                    good = list(hover) + [hover[p.names.index("panda_finger_joint1")]] * len(p.extra)
                    t_end = time.monotonic() + 2.0
                    while time.monotonic() < t_end:  # the flood is on when the signal comes
                        p.publish(names=names, positions=good)
                        time.sleep(0.001)

                    def during():
                        p.publish(names=names, positions=good)
                        time.sleep(0.001)
                res[label] = n2.stop_by_signal(sig, during)
            finally:
                e2 = n2.close()
            res[label.replace("_s", "_rc")] = e2["rc"]
            res["shm_left_" + label] = e2["shm_left"]
    res["load_after"] = load_line()
    print(format_report(res, args))
    if args.json:
        Path(args.json).write_text(json.dumps(res, indent=2))
    return 0


def format_report(r: dict, args) -> str:
    lines = [f"\nsoma_sim_node fuzz benchmark -- {r['machine']}",
             f"scene: {r['splats']} splats, cpu model (untrained), cam_front 320x240, rate_hz {args.rate_hz:g}, "
             f"render_rate_hz {args.render_rate_hz:g}",
             f"{r['load_before']} before, {r['load_after']} after", ""]
    if "resets" in r:
        row = "{:<42} {:>8} {:>16} {:>6} {:>6}  {}"
        lines.append(row.format("reset input", "answer", "RSS b/peak/a MB", "steps", "js in", "reply"))
        for x in r["resets"]:
            rss = f"{x['rss_before_mb']:.0f}/{x['rss_peak_mb']:.0f}/{x['rss_after_mb']:.0f}"
            steps = "-" if x["steps_meanwhile"] is None else str(x["steps_meanwhile"])
            lines.append(row.format(x["case"][:42], f"{x['seconds']:.3f} s", rss, steps, x["joint_states_meanwhile"],
                                    x["message"][:110]))
        worst = max(x["rss_peak_mb"] - x["rss_before_mb"] for x in r["resets"] if x["case"].startswith(("lying", "2M")))
        slow = max(x["seconds"] for x in r["resets"] if x["case"].startswith(("lying", "2M")))
        lines.append(f"lying-header and 2M-point resets: slowest answer {slow:.3f} s (target < 1 s), "
                     f"largest RSS rise {worst:.0f} MB (target < 100 MB)")
        lines.append("")
    if "flood" in r:
        f, b = r["flood"]["flood"], r["flood"]["baseline"]
        lines.append(f"{'':<42} {'100 Hz input':>14} {f'{args.flood_hz:.0f} Hz flood':>14} {'flood/target':>13}")
        lines.append(f"{'step rate, Hz (target ' + format(args.rate_hz, 'g') + ')':<42} {b['steps_per_s']:>14.1f} "
                     f"{f['steps_per_s']:>14.1f} {f['steps_per_s'] / args.rate_hz:>13.2f}")
        lines.append(f"{'image rate, Hz (target ' + format(args.render_rate_hz, 'g') + ')':<42} {b['images_per_s']:>14.1f} "
                     f"{f['images_per_s']:>14.1f} {f['images_per_s'] / args.render_rate_hz:>13.2f}")
        lines.append(f"{'joint states sent / received':<42} {b['sent']:>7}/{b['received']:<6} {f['sent']:>7}/{f['received']:<6}")
        lines.append(f"{'  dropped (newer replaced them) / rejected':<42} {b['dropped']:>7}/{b['rejected']:<6} "
                     f"{f['dropped']:>7}/{f['rejected']:<6}")
        fl = r["flood"]
        lines.append(f"{'node RSS before / peak / after the flood':<42} {fl['rss_before_mb']:.0f} / {fl['rss_peak_mb']:.0f} / "
                     f"{fl['rss_after_mb']:.0f} MB")
        lines.append("")
    if "sigterm_during_reset_s" in r:
        lines.append(f"second reset during a 150,000-splat reset: {r['busy_answer']!r} "
                     f"(first still running: {not r['first_done_at_sigterm']})")
        lines.append(f"SIGTERM with that reset running: exit after {r['sigterm_during_reset_s']:.2f} s (rc {r['rc_main']})")
        lines.append(f"SIGTERM during a 1 kHz flood: exit after {r['sigterm_during_flood_s']:.2f} s (rc {r['sigterm_during_flood_rc']})")
        lines.append(f"SIGINT idle: exit after {r['sigint_idle_s']:.2f} s (rc {r['sigint_idle_rc']})   target: < 2 s each")
        left = r["shm_left_main"] + r["shm_left_sigterm_during_flood_s"] + r["shm_left_sigint_idle_s"]
        lines.append(f"shared-memory files the three nodes had mapped that remain after exit: {left or 'none'} "
                     f"(fastrtps_port* lock files are shared by all participants on the machine)")
    return "\n".join(lines)


if __name__ == "__main__":
    sys.exit(main())
