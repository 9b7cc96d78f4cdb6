"""The live engine's own timing figures: per-step CPU time and the start-up calibration
that /soma/status reports beside the in-node times; the bench's extra fixed cameras."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from soma_ros.live import LIVE_PARAMETERS, LiveSimulator, live_kwargs, load_live, paced


@pytest.fixture(scope="module")
def live(untrained_run) -> LiveSimulator:
    return load_live(str(untrained_run[0]), str(untrained_run[1]))


def test_step_reports_thread_cpu_time(live):
    live.reset(live.bundle.splats)
    _, wall_ms = live.step(live.neutral_joint_vec())
    assert 0 < live.last_step_cpu_ms <= wall_ms * 1.05 + 0.5


def test_calibrate_measures_alone_and_leaves_the_running_state(live):
    live.reset(live.bundle.splats)
    vec = live.neutral_joint_vec()
    assert vec.shape == (len(live.required_joints),) and np.isfinite(vec).all()
    for _ in range(3):
        live.step(None)
    state, template, steps = live.snapshot()
    before = state.means.clone()
    t = live.calibrate(steps=3, renders=2)
    assert t.step_ms > 0 and t.render_ms > 0
    state2, template2, steps2 = live.snapshot()
    assert state2 is state and template2 is template and steps2 == steps == 3
    assert torch.equal(state2.means, before)
    with pytest.raises(ValueError, match="steps >= 1"):
        live.calibrate(steps=0)


def test_calibrate_paces_steps_and_renders_at_the_given_periods(live):
    """With periods, calibration runs its steps and renders on the node's grid (one warm-up call
    each, then the measured ones), not back to back, and restores the running state."""
    import time

    live.reset(live.bundle.splats)
    before = live.snapshot()[0].means.clone()
    t0 = time.monotonic()
    t = live.calibrate(steps=3, renders=2, step_period_s=0.08, render_period_s=0.06)
    took = time.monotonic() - t0
    assert took >= 3 * 0.08 + 2 * 0.06  # 4 steps 0.08 s apart, 3 renders 0.06 s apart
    assert t.step_ms > 0 and t.render_ms > 0
    assert torch.equal(live.snapshot()[0].means, before)
    with pytest.raises(ValueError, match="periods >= 0"):
        live.calibrate(step_period_s=-1.0)


def test_paced_yields_on_a_grid_that_a_slow_iteration_does_not_shift():
    import time

    t0 = time.monotonic()
    starts = []
    for k in paced(0.1, 4):
        starts.append(time.monotonic() - t0)
        if k == 1:
            time.sleep(0.14)  # one slow iteration: the next starts at once, the last on the grid
    assert [k for k in paced(0.0, 3)] == [0, 1, 2]
    assert starts[1] >= 0.1 and starts[2] >= 0.24 and starts[3] >= 0.3
    assert starts[3] - starts[2] < 0.09  # back on the grid (0.06 s later), not a full period after


def test_live_kwargs_maps_every_node_parameter_and_names_missing_ones():
    """The node and the bench build the engine from the same parameter -> keyword table."""
    import inspect

    import yaml

    from soma_ros.paths import config_dir

    values = yaml.safe_load((config_dir() / "nodes" / "sim_node.yaml").read_text())["/**"]["ros__parameters"]
    k = live_kwargs(values)
    assert set(k) == set(LIVE_PARAMETERS.values()) <= set(inspect.signature(load_live).parameters)
    assert isinstance(k["passive_exempt_grasped"], bool) and isinstance(k["settle_s"], float)
    with pytest.raises(KeyError, match="settle_time_s"):
        live_kwargs({n: v for n, v in values.items() if n != "settle_time_s"})


def test_bench_engine_uses_the_node_settings(untrained_run):
    """The bench's engine section builds the engine as the node does (its parameter file's
    settling and passive-object defaults, with --param overrides)."""
    from benchmarks.bench_live import node_engine_kwargs

    k = node_engine_kwargs()
    assert k["settle_s"] > 0 and k["passive_friction"] >= 0
    off = node_engine_kwargs(["settle_time_s:=0.0", "passive_friction:=-1.0"])
    assert off["settle_s"] == 0.0 and off["passive_friction"] == -1.0
    a = load_live(str(untrained_run[0]), str(untrained_run[1]), **k)
    b = load_live(str(untrained_run[0]), str(untrained_run[1]), **off)
    assert a.settle_steps > 0 and b.settle_steps == 0


def test_bench_adds_fixed_cameras_looking_at_the_object(untrained_run, tmp_path):
    from benchmarks.bench_live import with_cameras
    from soma_ros.core.scene_bundle import SceneBundle

    folder, names = with_cameras(untrained_run[1], 3, tmp_path / "scene3")
    assert names == ["cam_front", "cam_left", "cam_right"]
    three = load_live(str(untrained_run[0]), str(folder), camera_names=names)
    state, template, _ = three.snapshot()
    out, cams = three.render(state, template, None)
    assert out.rgb.shape[0] == 3
    cover = out.alpha.flatten(1).gt(0.5).float().mean(1)
    assert (cover > 0.005).all(), cover  # the rope is in every view
    assert not torch.equal(out.rgb[1], out.rgb[2])  # from different sides
    assert len(SceneBundle.load(folder).cameras) == 4  # the wrist camera is kept
    same, one = with_cameras(untrained_run[1], 1, tmp_path / "scene1")
    assert str(same) == str(untrained_run[1]) and one == ["cam_front"]
