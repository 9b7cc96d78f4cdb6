"""Packaging: package.xml's dependency kinds, `soma` after an ament_python install, `soma --help`."""

from __future__ import annotations

import subprocess
import sys

import pytest

from conftest import ROOT


def test_package_xml_splits_run_time_and_test_dependencies():
    catkin_pkg = pytest.importorskip("catkin_pkg.package")
    pkg = catkin_pkg.parse_package(str(ROOT / "package.xml"))
    pkg.validate()
    run = {d.name for d in pkg.exec_depends} | {d.name for d in pkg.run_depends}
    test = {d.name for d in pkg.test_depends}
    test_only = {"python3-pytest", "python3-pytest-timeout", "python3-psutil", "python3-pytorch-msssim-pip",
                 "python3-mcap-pip", "python3-mcap-ros2-support-pip", "chromium"}
    assert test_only <= test and not (test_only & run), (test_only - test, test_only & run)
    assert {"rclpy", "sensor_msgs", "tf2_msgs", "std_msgs", "python3-viser-pip", "python3-torch"} <= run
    # nothing imported by the package at run time is only a test dependency
    for mod in ("psutil", "pytest", "mcap", "pytorch_msssim"):
        hits = subprocess.run(["grep", "-rlE", rf"^\s*(import|from) {mod}\b", "soma_ros", "trainer"], cwd=ROOT,
                              capture_output=True, text=True).stdout.split()
        assert not hits, f"{mod} is a test dependency but {hits} import it"


def test_soma_is_installed_where_ros2_run_finds_it(tmp_path):
    """What colcon's ament_python build does (setup.py install with setup.cfg's script dir):
    the console scripts land in lib/soma_ros, which is where `ros2 run soma_ros soma` looks."""
    src = tmp_path / "src"
    files = subprocess.run(["git", "ls-files", "-co", "--exclude-standard"], cwd=ROOT, capture_output=True,
                           text=True, check=True).stdout.split()
    for f in files:
        if f.startswith("test/") or not (ROOT / f).is_file():
            continue
        (src / f).parent.mkdir(parents=True, exist_ok=True)
        (src / f).write_bytes((ROOT / f).read_bytes())
    prefix = tmp_path / "install"
    r = subprocess.run([sys.executable, "setup.py", "-q", "install", "--prefix", str(prefix),
                        "--single-version-externally-managed", "--record", str(tmp_path / "record.txt")],
                       cwd=src, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]
    for script in ("soma", "soma_sim_node", "soma_bag_player", "soma_recorder"):
        assert (prefix / "lib" / "soma_ros" / script).is_file(), script
    assert (prefix / "share" / "soma_ros" / "package.xml").is_file()
    assert (prefix / "share" / "soma_ros" / "config" / "nodes" / "sim_node.yaml").is_file()
    site = next(prefix.glob("lib/python3*/site-packages"))
    out = subprocess.run([str(prefix / "lib" / "soma_ros" / "soma"), "--help"], capture_output=True, text=True,
                         env={"PYTHONPATH": str(site), "PATH": "/usr/bin:/bin"}, timeout=120, cwd=tmp_path)
    assert out.returncode == 0 and "view" in out.stdout, out.stderr[-2000:]


def test_soma_help_imports_no_command_module():
    """`soma --help` lists every command without importing one (so it answers fast; the time is
    measured by benchmarks/bench_view.py, not asserted here)."""
    code = ("import sys; from soma_ros.cli import build_parser\n"
            "assert all(c in build_parser(['--help']).format_help() for c in ('world', 'train', 'view'))\n"
            "heavy = [m for m in ('torch', 'rclpy', 'rosbags', 'mujoco', 'viser') if m in sys.modules]\n"
            "cmds = [m for m in sys.modules if m.startswith('soma_ros.commands.')]\n"
            "print(heavy, cmds)")
    r = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=120,
                       env={"PYTHONPATH": str(ROOT), "PATH": "/usr/bin:/bin"})
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == "[] []", r.stdout
