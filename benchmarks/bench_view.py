"""`soma view --node` beside a live node: does the viewer slow the twin down? And `soma --help`'s time.

    python -m benchmarks.bench_view [--splats 13000] [--seconds 20] [--rounds 2] [--browser]

1. ``soma --help`` and ``soma view --help``: wall time of the whole process (interpreter
   start included), median of 5 runs.
2. A soma_sim_node on a random-weight ``cpu`` model with ``--splats`` splats (default
   13,000), 2 cameras at 160x120, its default rates (30 Hz steps, 10 Hz images, 5 Hz splat
   clouds), driven by /joint_states at 30 Hz from this process. Its step rate is measured
   from /soma/status (steps counted over the window) with no viewer, then with
   ``soma view --node`` attached (subscribed to the splats, images, status, TF), in
   alternating windows (no viewer, viewer, no viewer, ...) so a drift in the machine's load
   hits both alike. ``--browser`` also opens the view's page in headless Chromium (the
   browser's WebGL then runs on the same CPUs; normally it is on the user's machine).

Prints the rates, their ratio and the CPU use of each process, with the machine and its
load average (other users of shared cores count).
"""

from __future__ import annotations

import argparse
import os
import re
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Optional, Sequence

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def cli_times(n: int = 5) -> dict[str, float]:
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    out = {}
    for args in (["--help"], ["view", "--help"]):
        ts = []
        for _ in range(n):
            t0 = time.perf_counter()
            subprocess.run([sys.executable, "-m", "soma_ros.cli", *args], env=env, capture_output=True, check=True)
            ts.append(time.perf_counter() - t0)
        out["soma " + " ".join(args)] = statistics.median(ts)
    return out


def _steps_over(b, vec, seconds: float) -> tuple[float, int]:
    """(steps per second from /soma/status over `seconds`, status messages seen) while holding `vec`."""
    st0 = b.probe.last_status()
    t0 = time.monotonic()
    b.probe.hold(vec, lambda: False, seconds)
    st1 = b.probe.last_status()
    dt = time.monotonic() - t0
    if st1.step < st0.step:
        raise RuntimeError("the node restarted its scene during the window; rerun")
    return (st1.step - st0.step) / dt, len(b.probe.status)


def _start_viewer(domain: int, browser: bool, log: Path):
    from soma_ros.nodes.testing import ros_env

    f = open(log, "w")
    proc = subprocess.Popen([sys.executable, "-m", "soma_ros.cli", "view", "--node", "--port", "0"],
                            env=ros_env(domain, {"PYTHONPATH": str(ROOT)}), stdout=f, stderr=subprocess.STDOUT,
                            cwd=ROOT, process_group=0)
    deadline = time.monotonic() + 120
    url = None
    while time.monotonic() < deadline and url is None:
        m = re.search(r"serving (http://\S+)", log.read_text())
        url = m.group(1) if m else None
        if proc.poll() is not None:
            raise RuntimeError(f"soma view --node exited:\n{log.read_text()[-3000:]}")
        time.sleep(0.5)
    if url is None:
        raise RuntimeError("soma view --node did not start")
    chrome = None
    if browser:
        from soma_ros.viewer.screenshot import CHROMIUM_FLAGS, find_browser

        profile = tempfile.mkdtemp(prefix="soma_bench_chromium_")
        chrome = subprocess.Popen([find_browser(), *CHROMIUM_FLAGS, f"--user-data-dir={profile}", url],
                                  stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, process_group=0)
    return proc, chrome


def _stop(proc) -> None:
    if proc is not None and proc.poll() is None:
        proc.terminate()
        try:
            proc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(timeout=20)


def main(argv: Optional[Sequence[str]] = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--splats", type=int, default=13000)
    ap.add_argument("--seconds", type=float, default=20.0, help="length of one measuring window")
    ap.add_argument("--rounds", type=int, default=2, help="pairs of windows (no viewer, viewer)")
    ap.add_argument("--browser", action="store_true", help="also open the page in headless Chromium")
    args = ap.parse_args(argv)

    import psutil

    from benchmarks.bench_live import CpuMeter, Poser, _Bench, load_line, machine_line
    from soma_ros.core.scenes import write_untrained_run
    from soma_ros.live import load_live

    print(f"machine: {machine_line(1)}")
    print(f"at start: {load_line()}")
    for what, t in cli_times().items():
        print(f"{what:<20} {t * 1e3:7.0f} ms (median of 5, whole process)")

    tmp = Path(tempfile.mkdtemp(prefix="soma_bench_view_"))
    run = write_untrained_run(tmp / "run", n=args.splats, width=160, height=120)
    live = load_live(str(run[0]), str(run[1]))
    poser = Poser(live.robot, live.base_to_sim.matrix(), live.required_joints, live.bundle.gravity)
    m = live.template.means.double().numpy()
    hover = poser.solve((float(m[:, 0].mean()), float(m[:, 1].mean()), float(m[:, 2].max()) + 0.25))
    b = _Bench(run, [], live.required_joints, ("cam_front",), splats=False)
    rows = []
    viewer = chrome = None
    try:
        b.started(hover, ("status",))
        b.probe.hold(hover, lambda: False, 10.0)  # warm up
        for r in range(args.rounds):
            for with_viewer in (False, True):
                if with_viewer:
                    log = tmp / f"viewer_{r}.log"
                    viewer, chrome = _start_viewer(b.domain, args.browser, log)
                    # its start-up (the robot's meshes loaded from /robot_description) is not measured
                    if not b.probe.hold(hover, lambda: "robot drawn" in log.read_text(), 120.0):
                        raise RuntimeError(f"soma view --node did not draw the robot:\n{log.read_text()[-3000:]}")
                    b.probe.hold(hover, lambda: False, 5.0)  # it draws its first frames
                    view_ps = psutil.Process(viewer.pid)
                    view_ps.cpu_percent(None)
                meter = CpuMeter(b.node.proc.pid)  # the node with its render process
                rate, _ = _steps_over(b, hover, args.seconds)
                cpu_node = meter.stop()["node_cores"]
                cpu_view = view_ps.cpu_percent(None) / 100.0 if with_viewer else 0.0
                rows.append((with_viewer, rate, cpu_node, cpu_view, os.getloadavg()[0]))
                print(f"round {r + 1} {'viewer   ' if with_viewer else 'no viewer'}: node {rate:6.2f} steps/s, "
                      f"node CPU {cpu_node:.2f} cores, viewer CPU {cpu_view:.2f} cores, load {rows[-1][4]:.2f}",
                      flush=True)
                if with_viewer:
                    _stop(chrome)
                    _stop(viewer)
                    viewer = chrome = None
    finally:
        _stop(chrome)
        _stop(viewer)
        b.close()
    without = np.mean([r[1] for r in rows if not r[0]])
    with_ = np.mean([r[1] for r in rows if r[0]])
    print(f"\n{args.splats} splats, {args.rounds} x {args.seconds:.0f} s windows each; node target 30 steps/s")
    print(f"  node step rate without viewer: {without:.2f} steps/s")
    print(f"  node step rate with viewer:    {with_:.2f} steps/s  (ratio {with_ / without:.3f}, "
          f"{'within' if abs(with_ / without - 1) <= 0.10 else 'NOT within'} 10 %)")
    print(f"  viewer CPU {np.mean([r[3] for r in rows if r[0]]):.2f} cores; browser: "
          f"{'headless Chromium on this machine' if args.browser else 'none attached'}")
    print(f"at end: {load_line()}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
