"""`soma robot check` via subprocess with the venv python."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
PANDA = ROOT / "soma_ros" / "resources" / "robots" / "franka_panda" / "panda.urdf"
ARX5 = ROOT / "soma_ros" / "resources" / "robots" / "arx5" / "X5.urdf"


def _soma(*args: str) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONPATH=str(ROOT), OMP_NUM_THREADS="1")
    return subprocess.run(
        [sys.executable, "-m", "soma_ros.cli", "robot", "check", *args],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )


def test_check_panda_urdf_args() -> None:
    r = _soma("--urdf", str(PANDA), "--ee-link", "panda_hand", "--gripper-joints", "panda_finger_joint1",
              "--samples", "2", "--seed", "1")
    assert r.returncode == 0, r.stderr
    out = r.stdout
    assert "--[panda_joint7: revolute" in out and "--[panda_hand_joint: fixed]--> panda_hand" in out
    assert "mimic: panda_finger_joint2 = 1 * panda_finger_joint1" in out
    assert "opening range [0.0000, 0.0800] m" in out
    # Panda hand at zero: 0.088 m forward, 0.926 m up
    assert "q = 0        xyz [+0.0880 +0.0000 +0.9260]" in out
    assert "random #1" in out and "control points: 30" in out
    assert out.rstrip().endswith("OK")


def test_check_arx5_config() -> None:
    r = _soma("--config", "config/robots/arx5.yaml", "--samples", "1")
    assert r.returncode == 0, r.stderr
    assert "(not in the URDF: gripper)" in r.stdout
    assert "--[gripper_fixed_joint: fixed]--> eef_link" in r.stdout
    r = _soma("--urdf", str(ARX5), "--ee-link", "eef_link")
    assert r.returncode == 0, r.stderr
    assert "gripper: none configured" in r.stdout


@pytest.mark.parametrize(
    "args, expect",
    [
        (["--urdf", str(PANDA), "--ee-link", "panda_hnd"], "ee_link 'panda_hnd' is not a link of robot 'panda'"),
        (["--urdf", str(PANDA), "--ee-link", "panda_hand", "--gripper-joints", "finger"], "gripper joint 'finger' is not a joint"),
        (["--urdf", "nowhere.urdf", "--ee-link", "x"], "URDF file not found: nowhere.urdf"),
        (["--ee-link", "x"], "give --urdf FILE and --ee-link LINK, or --config"),
    ],
)
def test_check_fails_with_one_line(args, expect) -> None:
    r = _soma(*args)
    assert r.returncode == 2
    assert r.stdout == ""
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in r.stderr, r.stderr
    assert lines[0].startswith("soma robot: error: ") and expect in lines[0]


def test_check_broken_urdf(tmp_path) -> None:
    broken = tmp_path / "broken.urdf"
    text = PANDA.read_text().replace('<child link="panda_link4"/>', '<child link="panda_link44"/>')
    broken.write_text(text)
    r = _soma("--urdf", str(broken), "--ee-link", "panda_hand")
    assert r.returncode == 2
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1, r.stderr
    assert "joint 'panda_joint4' names child link 'panda_link44', which is not defined" in lines[0]
    truncated = tmp_path / "truncated.urdf"
    truncated.write_text(PANDA.read_text()[:3000])
    r = _soma("--urdf", str(truncated), "--ee-link", "panda_hand")
    assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1
    assert "truncated.urdf: malformed XML" in r.stderr
