"""soma_sim_node refuses a bad start-up parameter with one line naming it, and exit status 2.

rclpy checks a ``--ros-args -p`` value against the declared type and range while the node
declares it, before any checkpoint is read, so these runs need no model.
"""

from __future__ import annotations

import subprocess
import sys

import pytest

from soma_ros.nodes.testing import ros_env, unique_domain_id

SIM = "soma_ros.nodes.sim_node"


@pytest.mark.parametrize("override, name, words", [
    ("rate_hz:=5000.0", "rate_hz", "out of range"),
    ("rate_hz:=fast", "rate_hz", "expecting type 'DOUBLE'"),
    ("rate_hz:=30", "rate_hz", "decimal point"),
    ("render_scale:=0.0", "render_scale", "out of range"),
    ("max_splats:=many", "max_splats", "expecting type 'INTEGER'"),
])
def test_a_bad_parameter_exits_2_with_one_line_naming_it(override, name, words):
    r = subprocess.run([sys.executable, "-m", SIM, "--ros-args", "-p", "checkpoint:=model.pt", "-p",
                        "scene:=scene_dir", "-p", override], env=ros_env(unique_domain_id()),
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 2, r.stdout[-2000:] + r.stderr[-2000:]
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1, r.stderr
    assert lines[0].startswith(f"soma_sim_node: error: parameter '{name}': "), lines[0]
    assert words in lines[0], lines[0]
    assert "Traceback" not in r.stderr + r.stdout
