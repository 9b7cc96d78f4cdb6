"""soma_msgs interfaces: the splat cloud layout, the reset service across
two OS processes, and soma_msgs in bags through rosbags without ROS."""

from __future__ import annotations

import subprocess
import sys
import textwrap

import numpy as np
import pytest
import torch

from soma_ros.core.cloud_layout import (
    POINT_STEP,
    REQUIRED_FIELDS,
    cloud_to_splats,
    pack_rgb,
    splat_field_specs,
    splats_to_records,
    unpack_rgb,
)
from soma_ros.core.scenes import synthetic_rope


def _rosbags_cloud(splats, frame="soma_sim"):
    from soma_ros.bagtypes import typestore

    ts = typestore()
    PointCloud2 = ts.types["sensor_msgs/msg/PointCloud2"]
    PointField = ts.types["sensor_msgs/msg/PointField"]
    Header = ts.types["std_msgs/msg/Header"]
    Time = ts.types["builtin_interfaces/msg/Time"]
    rec = splats_to_records(splats)
    return PointCloud2(
        header=Header(stamp=Time(sec=1, nanosec=2), frame_id=frame), height=1, width=len(rec),
        fields=[PointField(name=f.name, offset=f.offset, datatype=f.datatype, count=f.count) for f in splat_field_specs()],
        is_bigendian=False, point_step=POINT_STEP, row_step=POINT_STEP * len(rec),
        data=np.frombuffer(rec.tobytes(), dtype=np.uint8), is_dense=True,
    )


def test_layout_matches_interface_definition():
    from soma_msgs.msg import SplatLayout

    assert SplatLayout.POINT_STEP == POINT_STEP
    assert tuple(SplatLayout.REQUIRED_FIELDS.split(",")) == REQUIRED_FIELDS
    specs = splat_field_specs()
    assert len(specs) == SplatLayout.NUM_FIELDS
    assert specs[-1].offset + 4 == POINT_STEP


def test_cloud_roundtrip_is_exact_and_rgb_is_packed():
    s = synthetic_rope(500, seed=3)
    back = cloud_to_splats(_rosbags_cloud(s))
    for name in ("means", "quats", "scales", "opacities", "sh_dc", "mass"):
        assert torch.equal(getattr(back, name), getattr(s, name).float()), name
    rgb = unpack_rgb(splats_to_records(s)["rgb"])
    expect = np.clip(np.rint(s.colors().numpy() * 255), 0, 255).astype(np.uint8)
    assert np.array_equal(rgb, expect)
    assert np.array_equal(unpack_rgb(pack_rgb(np.array([[1.0, 0.0, 0.5]]))), [[255, 0, 128]])


@pytest.mark.parametrize(
    "mutate, message",
    [
        (lambda c: setattr(c, "fields", [f for f in c.fields if f.name != "opacity"]), "opacity"),
        (lambda c: setattr(c, "data", c.data[:-10]), "expected"),
        (lambda c: setattr(c, "width", 0), "empty"),
        (lambda c: setattr(c, "is_bigendian", True), "big-endian"),
    ],
)
def test_malformed_clouds_are_refused_with_a_named_problem(mutate, message):
    c = _rosbags_cloud(synthetic_rope(50))
    mutate(c)
    with pytest.raises(ValueError, match=message):
        cloud_to_splats(c)


def test_non_finite_splats_are_refused():
    s = synthetic_rope(50)
    s.means[7, 1] = float("nan")
    with pytest.raises(ValueError, match="non-finite"):
        cloud_to_splats(_rosbags_cloud(s))


def test_reset_service_across_two_processes(ros_env, untrained_run):
    """A server process (soma_sim_node) and a client process (soma scene reset)
    exchange a ResetScene call carrying 13,000 splats; the server reports the
    exact count back."""
    from conftest import sim_node_args
    from soma_ros.nodes.testing import RosProcess

    args = sim_node_args(*untrained_run, "-p", "render_rate_hz:=0.0", "-p", "splat_rate_hz:=0.0")
    with RosProcess("soma_ros.nodes.sim_node", args, ros_env, name="server") as server:
        client = subprocess.run(
            [sys.executable, "-m", "soma_ros.cli", "scene", "reset", "--synthetic", "13000", "--timeout", "60"],
            env=ros_env, capture_output=True, text=True, timeout=120,
        )
        assert client.returncode == 0, client.stdout + client.stderr + server.output()
        assert "success=True num_splats=13000 sent=13000" in client.stdout

        refused = subprocess.run(
            [sys.executable, "-m", "soma_ros.cli", "scene", "reset", "--empty", "--timeout", "60"],
            env=ros_env, capture_output=True, text=True, timeout=120,
        )
        assert refused.returncode == 1, refused.stdout + refused.stderr
        # Refused, with a message, and the old scene (13,000 splats) keeps running.
        assert "success=False num_splats=13000" in refused.stdout
        assert "neither splats (0 points) nor a ply_path" in refused.stdout
        assert server.alive(), server.output()


def test_soma_msgs_in_a_bag_without_ros(tmp_path):
    """Write a bag holding soma_msgs/msg/SimStatus and a splat cloud with rosbags,
    read it back, all in a process that never imports rclpy."""
    script = textwrap.dedent(
        f"""
        import sys
        import numpy as np
        from rosbags.rosbag2 import Writer
        from rosbags.highlevel import AnyReader
        from soma_ros.bagtypes import typestore
        from soma_ros.core.cloud_layout import cloud_to_splats
        from soma_ros.core.scenes import synthetic_rope
        sys.path.insert(0, {str(__import__('pathlib').Path(__file__).parent)!r})
        from test_interfaces import _rosbags_cloud

        ts = typestore()
        Status = ts.types["soma_msgs/msg/SimStatus"]
        Header = ts.types["std_msgs/msg/Header"]
        Time = ts.types["builtin_interfaces/msg/Time"]
        bag = {str(tmp_path / 'bag')!r}
        splats = synthetic_rope(1234)
        with Writer(bag, version=9) as w:
            c1 = w.add_connection("/soma/status", Status.__msgtype__, typestore=ts)
            c2 = w.add_connection("/soma/splats", "sensor_msgs/msg/PointCloud2", typestore=ts)
            for i in range(3):
                st = Status(header=Header(stamp=Time(sec=i, nanosec=0), frame_id="soma_sim"), state="running",
                            step=i, num_splats=1234, step_time_ms=1.5, render_time_ms=2.5, step_cpu_ms=1.25,
                            render_cpu_ms=2.0, engine_step_ms=1.25, engine_render_ms=2.0, joint_state_lag_ms=0.0,
                            step_rate_hz=30.0, image_rate_hz=10.0, joint_states_received=i, joint_states_rejected=0,
                            joint_states_dropped=0,
                            failure_restarts=0, settles=0)
                w.write(c1, i * 10**9, ts.serialize_cdr(st, Status.__msgtype__))
            w.write(c2, 5, ts.serialize_cdr(_rosbags_cloud(splats), "sensor_msgs/msg/PointCloud2"))
        steps, n = [], None
        with AnyReader([__import__('pathlib').Path(bag)], default_typestore=ts) as r:
            for conn, t, raw in r.messages():
                msg = r.deserialize(raw, conn.msgtype)
                if conn.msgtype == "soma_msgs/msg/SimStatus":
                    steps.append(msg.step); assert msg.state == "running" and msg.num_splats == 1234
                else:
                    n = len(cloud_to_splats(msg))
        assert steps == [0, 1, 2], steps
        assert n == 1234, n
        assert "rclpy" not in sys.modules, "rclpy was imported"
        print("BAG_OK")
        """
    )
    r = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0 and "BAG_OK" in r.stdout, r.stdout + r.stderr
