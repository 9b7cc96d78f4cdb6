"""The live engine without ROS: JointStateFilter and LiveSimulator.

LiveSimulator runs the test run's untrained run (random-weight `cpu` model,
2,000-splat synthetic rope, robot base on the table at (0, 0, 0.75)). What a
random model can show: the initial state is an exact fixed point, so with the
gripper out of the robot effect's reach (radius 5 cm) nothing moves, bit for
bit; once the gripper's control points reach the rope, the robot force acts
exactly on the splats within reach and the rope moves. (Which splats end up
moving most is the network's business: a random network propagates the push
through the hierarchy's root to the whole rope, so "the grasped part lifts,
the far end stays" is a trained-model property, tested in test_sim_node.py.)
"""

from __future__ import annotations

import math
import re
import threading
import time

import numpy as np
import pytest
import torch

from soma_ros.live import JointStateFilter, JointStateRejected, LiveSimulator, load_live

ARM = [f"panda_joint{i}" for i in range(1, 8)]
REQUIRED = ARM + ["panda_finger_joint1"]
TABLE_Z = 0.75  # synthetic_bundle: table top, robot base at (0, 0, TABLE_Z)
ROBOT_RADIUS = 0.05  # config/models/cpu.yaml: effects.robot.radius


# --------------------------------------------------------------------------- JointStateFilter
def _vec(k: float = 0.0) -> list[float]:
    return [0.1 * i + k for i in range(len(REQUIRED))]


def test_filter_accepts_any_order_and_ignores_unknown_extra_joints():
    f = JointStateFilter(REQUIRED)
    names = list(reversed(REQUIRED)) + ["panda_finger_joint2", "some_other_joint"]
    pos = list(reversed(_vec())) + [0.04, float("nan")]  # a NaN on a joint nobody needs is fine
    out = f.push(names, pos, 100)
    assert np.array_equal(out, _vec())
    assert (f.received, f.rejected) == (1, 0)
    assert np.array_equal(f.sample(), _vec())


@pytest.mark.parametrize(
    "names, positions, stamp, reason",
    [
        (REQUIRED, _vec()[:-1], 200, "8 names but 7 positions"),
        (REQUIRED + ["extra"], _vec(), 200, "9 names but 8 positions"),
        (REQUIRED[:3] + ["panda_joint3"] + REQUIRED[4:], _vec(), 200, "duplicate joint name 'panda_joint3'"),
        (["not_a_panda_joint"] + REQUIRED[1:], _vec(), 200, "missing joints: panda_joint1"),
        ([], [], 200, "missing joints: panda_joint1, panda_joint2"),
        (REQUIRED, _vec()[:2] + [float("nan")] + _vec()[3:], 200, "non-finite values for: panda_joint3"),
        (REQUIRED, _vec()[:7] + [float("inf")], 200, "non-finite values for: panda_finger_joint1"),
        (REQUIRED, [-math.inf] + _vec()[1:], 200, "non-finite values for: panda_joint1"),
        (REQUIRED, _vec()[:4] + [1e39] + _vec()[5:], 200, "non-finite values for: panda_joint5"),  # inf in float32
        (REQUIRED, _vec(), 99, "stamp went backwards by 0.0 ms"),
        (REQUIRED, _vec(), 100 - 5_000_000, "stamp went backwards by 5.0 ms"),
    ],
)
def test_filter_rejects_with_a_named_reason_and_keeps_its_history(names, positions, stamp, reason):
    f = JointStateFilter(REQUIRED)
    f.push(REQUIRED, _vec(), 100)
    with pytest.raises(JointStateRejected, match="^" + reason.replace("(", r"\(")) as exc:
        f.push(names, positions, stamp)
    assert isinstance(exc.value, ValueError)
    assert (f.received, f.rejected) == (2, 1)
    assert f.last_reason == str(exc.value)
    assert f.newest_stamp_ns() == 100
    assert np.array_equal(f.sample(), _vec())  # the rejected message left no trace


def test_filter_rejects_stamps_from_the_future_only_when_asked():
    f = JointStateFilter(REQUIRED, max_future_s=1.0)
    now = 10**18
    f.push(REQUIRED, _vec(), now + 900_000_000, now_ns=now)  # 0.9 s ahead: clock skew, accepted
    with pytest.raises(JointStateRejected, match=r"stamp is 3600.000 s ahead of the clock"):
        f.push(REQUIRED, _vec(1.0), now + 3600 * 10**9, now_ns=now)
    # the future stamp did not lock the stream: the next correctly stamped message is taken
    f.push(REQUIRED, _vec(2.0), now + 950_000_000, now_ns=now + 10_000_000)
    assert np.array_equal(f.sample(), _vec(2.0))
    assert (f.received, f.rejected) == (3, 1)
    # without a clock (or without a bound) the check is off, as before
    JointStateFilter(REQUIRED).push(REQUIRED, _vec(), now + 3600 * 10**9, now_ns=now)
    JointStateFilter(REQUIRED, max_future_s=1.0).push(REQUIRED, _vec(), now + 3600 * 10**9)


def test_filter_interpolates_by_stamp_and_holds_at_the_ends():
    f = JointStateFilter(REQUIRED)
    assert f.sample() is None and not f.has_data
    a, b, c = np.array(_vec(0.0)), np.array(_vec(1.0)), np.array(_vec(-3.0))
    f.push(REQUIRED, a, 1_000)
    assert np.array_equal(f.sample(0), a) and np.array_equal(f.sample(5_000), a)  # one entry: held
    f.push(REQUIRED, b, 2_000)
    f.push(REQUIRED, c, 4_000)
    assert np.allclose(f.sample(1_500), 0.5 * a + 0.5 * b)
    assert np.allclose(f.sample(1_250), 0.75 * a + 0.25 * b)
    assert np.allclose(f.sample(3_000), 0.5 * b + 0.5 * c)
    assert np.array_equal(f.sample(2_000), b)  # exact at a stamp
    assert np.array_equal(f.sample(10), a)  # before the history: the oldest
    assert np.array_equal(f.sample(10**12), c)  # after: the newest
    assert np.array_equal(f.sample(None), c)
    f.push(REQUIRED, a, 4_000)  # an equal stamp is not "backwards"
    assert np.array_equal(f.sample(), a)
    s = f.sample()
    s[:] = 99.0  # samples are copies
    assert np.array_equal(f.sample(), a)
    f.clear()
    assert f.sample() is None and f.newest_stamp_ns() is None


def test_filter_history_is_bounded():
    f = JointStateFilter(REQUIRED, history=16)
    for k in range(10_000):
        f.push(REQUIRED, _vec(k), k)
    assert len(f._hist) == 16
    assert np.array_equal(f.sample(0), _vec(10_000 - 16))  # older entries are gone
    assert f.received == 10_000


def test_filter_needs_required_joints():
    with pytest.raises(ValueError, match="at least one required joint"):
        JointStateFilter([])


# --------------------------------------------------------------------------- LiveSimulator
@pytest.fixture(scope="module")
def live(untrained_run) -> LiveSimulator:
    return load_live(str(untrained_run[0]), str(untrained_run[1]))


@pytest.fixture(scope="module")
def poser(live):
    from benchmarks.bench_live import Poser

    return Poser(live.robot, live.base_to_sim.matrix(), live.required_joints, live.bundle.gravity)


@pytest.fixture
def fresh(live) -> LiveSimulator:
    live.reset(live.bundle.splats)
    return live


def _rope_axis(live) -> tuple[np.ndarray, float, float]:
    m = live.bundle.splats.means.double().numpy()
    return m, float(m[:, 0].min()), float(m[:, 0].max())


def test_required_joints_action_and_gripper_state(live, poser):
    assert live.required_joints == REQUIRED
    vec = poser.solve((0.5, 0.02, TABLE_Z + 0.2), finger=0.04)
    q = torch.tensor(vec, dtype=live.robot.dtype)[None]
    act = live.action(vec)
    assert act.control_points.shape == (30, 3)
    # the control points are the robot's (base frame) moved by the scene's robot base: (0, 0, 0.75)
    cp_base = live.robot.control_points(q, torch.tensor([0.08]))[0].double()
    assert torch.allclose(act.control_points.double(), cp_base + torch.tensor([0.0, 0.0, TABLE_Z], dtype=torch.float64),
                          atol=1e-5)
    assert np.allclose(act.control_points.double().mean(0).numpy(), (0.5, 0.02, TABLE_Z + 0.2), atol=2e-3)
    assert float(act.gripper) == pytest.approx(1.0)  # 2 x 0.04 m = fully open
    assert float(live.action(poser.with_finger(vec, 0.0)).gripper) == pytest.approx(0.0)
    assert float(live.action(poser.with_finger(vec, 0.02)).gripper) == pytest.approx(0.5)
    # fingers closing: the two jaws' control points approach each other along y
    span = lambda v: float(np.ptp(live.action(v).control_points[:, 1].numpy()))  # noqa: E731
    assert span(poser.with_finger(vec, 0.04)) > span(poser.with_finger(vec, 0.0)) + 0.07


def test_at_rest_with_the_robot_far_away_nothing_moves_for_100_steps(fresh, poser):
    state0, template, steps = fresh.snapshot()
    assert steps == 0 and template is fresh.bundle.splats
    far = poser.solve((0.3, 0.35, TABLE_Z + 0.45))
    assert _min_dist_to_cp(fresh, far, state0.means) > 0.3
    for k in range(100):
        state, ms = fresh.step(far if k % 2 else None)  # robot present or absent: same rest
        assert ms > 0
    assert fresh.snapshot()[2] == 100 and state.step == 100
    assert torch.equal(state.means, state0.means), float((state.means - state0.means).abs().max())
    assert torch.equal(state.covs, state0.covs)
    assert torch.equal(state.quats, state0.quats)
    # and the initial state is the template (up to float rounding of the hierarchy's carry)
    assert torch.allclose(state0.means, template.means, atol=1e-6)


def _min_dist_to_cp(live, vec, means) -> float:
    cp = live.action(vec).control_points.double()
    return float(torch.cdist(means.double(), cp).min())


def test_gripper_out_of_reach_moves_nothing_and_through_the_rope_moves_it(fresh, poser):
    """A sweep 7 cm above the rope (control points just beyond the 5 cm reach) leaves every
    splat bit-exactly in place; the same sweep lowered into the rope moves it. On the first
    step in contact the robot force acts on the splats within reach of the gripper and on
    no splat beyond it."""
    live = fresh
    state0 = live.snapshot()[0]
    x0 = state0.means
    m, x_lo, x_hi = _rope_axis(live)
    top = float(m[:, 2].max())
    high = poser.line((x_lo + 0.05, 0.02, top + 0.07), (x_hi - 0.05, 0.02, top + 0.07), 25)
    for v in high + high[::-1]:
        assert _min_dist_to_cp(live, v, x0) > ROBOT_RADIUS
        state, _ = live.step(v)
    assert torch.equal(state.means, x0)

    # descend at the rope's left quarter
    g = (x_lo + 0.25 * (x_hi - x_lo), float(np.median(m[:, 1])), float(np.median(m[:, 2])))
    down = poser.line((g[0], g[1], g[2] + 0.12), g, 30, q0=high[0])
    first_contact = None
    for k, v in enumerate(down):
        if first_contact is None and _min_dist_to_cp(live, v, live.snapshot()[0].means) < ROBOT_RADIUS:
            first_contact = k
            state = live.snapshot()[0]
            act = live.action(v)
            with torch.no_grad():
                f_robot = live.sim.forces(state, act) - live.sim.forces(state, None)
            d = torch.cdist(state.means.double(), act.control_points.double()).min(1).values
            pushed = f_robot.norm(dim=1) > 0
            assert pushed.any()
            assert not pushed[d >= ROBOT_RADIUS].any(), "robot force beyond the effect's reach"
            assert bool((pushed == (d < ROBOT_RADIUS)).float().mean() > 0.5)
        state, _ = live.step(v)
    assert first_contact is not None and first_contact > 5  # the descent starts out of reach
    assert torch.isfinite(state.means).all()
    disp = (state.means - x0).norm(dim=1)
    assert float(disp.max()) > 1e-3, "the gripper went through the rope and nothing moved"
    # the published splats follow the state
    sp = live.current_splats()
    assert torch.equal(sp.means, state.means) and len(sp) == len(x0)
    assert torch.allclose(sp.covariances(), state.covs, atol=1e-9)


def test_settling_makes_a_moved_object_still_again_and_only_with_the_robot_away(untrained_run, poser):
    """After the gripper has pushed the rope and left, the random network keeps it creeping (its
    response is subtracted only in the initial configuration). Settling (robot out of reach and
    every splat slower than settle_speed for settle_s) restarts from the current configuration:
    the positions carry over and from then on the rope is bit-exactly still. Never while the
    robot is within reach."""
    live = load_live(str(untrained_run[0]), str(untrained_run[1]), settle_s=40 / 30, settle_speed=100.0)
    assert live.settle_steps == 40
    m, x_lo, x_hi = _rope_axis(live)
    g = (x_lo + 0.25 * (x_hi - x_lo), float(np.median(m[:, 1])), float(np.median(m[:, 2])))
    top = float(m[:, 2].max())
    high = poser.line((x_lo + 0.05, 0.02, top + 0.07), (x_lo + 0.06, 0.02, top + 0.07), 2)[0]
    down = poser.line((g[0], g[1], g[2] + 0.12), g, 30, q0=high)
    high = down[0]
    x0 = live.snapshot()[0].means
    for _ in range(45):  # at rest where the episode started: an exact fixed point already, nothing to settle
        st, _ = live.step(high)
    assert live.settles == 0 and torch.equal(st.means, x0)
    for v in down:  # 30 poses, in reach from about the 6th: never 40 quiet steps
        live.step(v)
    up = down[::-1]
    for v in up:
        live.step(v)
    assert live.settles == 0
    k = 0
    while live.settles == 0 and k < 60:  # out of reach since about the 25th pose up
        live.step(high)
        k += 1
    assert live.settles == 1 and k < 40
    n = live.settles
    # (a) without settling the same history creeps on
    ref = load_live(str(untrained_run[0]), str(untrained_run[1]))
    for v in [high] * 45 + down + up + [high] * k:
        ref.step(v)
    a, _ = ref.step(high)
    b, _ = ref.step(high)
    assert not torch.equal(a.means, b.means), "the random model did not creep: nothing to test"
    # (b) with settling: still, bit for bit, and no further settle needed to stay so
    s0, _ = live.step(high)
    for _ in range(25):
        s1, _ = live.step(high)
    assert torch.equal(s1.means, s0.means)
    assert live.settles >= n
    # the settled configuration is where the rope was (not the initial scene)
    assert float((s0.means - live.bundle.splats.means.to(s0.means.dtype)).norm(dim=-1).max()) > 1e-3
    # a reset zeroes the count; a non-positive speed is refused
    live.reset(live.bundle.splats)
    assert live.settles == 0
    with pytest.raises(ValueError, match="settle"):
        load_live(str(untrained_run[0]), str(untrained_run[1]), settle_s=1.0, settle_speed=0.0)


def test_passive_rule_is_a_live_option_and_stops_the_root_after_a_push(untrained_run, poser):
    """``passive_friction``: None keeps the checkpoint's setting (off), a number turns the
    passive-object rule on, a negative one off. With it, after the gripper has pushed the rope
    and left, the object's translation (the root) comes to rest on the table."""
    ck, sc = str(untrained_run[0]), str(untrained_run[1])
    assert load_live(ck, sc).sim.config.dynamics.passive_friction is None
    assert load_live(ck, sc, passive_friction=-1.0).sim.config.dynamics.passive_friction is None
    every_step = load_live(ck, sc, passive_friction=0.5, passive_exempt_grasped=False).sim.config.dynamics
    assert every_step.passive_exempt == []
    live = load_live(ck, sc, passive_friction=0.5)
    dyn = live.sim.config.dynamics
    assert dyn.passive_friction == 0.5 and dyn.passive_exempt == ["robot"] and dyn.passive_exempt_closed
    m, x_lo, x_hi = _rope_axis(live)
    g = (x_lo + 0.25 * (x_hi - x_lo), float(np.median(m[:, 1])), float(np.median(m[:, 2])))
    top = float(m[:, 2].max())
    high = poser.line((x_lo + 0.05, 0.02, top + 0.07), (x_lo + 0.06, 0.02, top + 0.07), 2)[0]
    down = poser.line((g[0], g[1], g[2] + 0.12), g, 30, q0=high)
    roots = []
    for v in [down[0]] * 5 + down + down[::-1] + [down[0]] * 40:
        st, _ = live.step(v)
        roots.append(st.positions[-1].clone())
    moved = max(float((r - roots[0]).norm()) for r in roots)
    assert moved > 1e-4, "the push did not move the rope: nothing to test"
    assert torch.equal(roots[-1], roots[-10]), "the root still moves 30 steps after the robot left"


def test_a_step_that_leaves_the_workspace_raises_and_keeps_the_last_state(untrained_run, poser):
    """max_travel_m: a step putting a splat further than that outside the initial scene's
    bounding sphere raises SimulationDiverged and the running state stays the last good one."""
    from soma_ros.live import SimulationDiverged

    live = load_live(str(untrained_run[0]), str(untrained_run[1]), max_travel_m=0.002)
    m, x_lo, x_hi = _rope_axis(live)
    g = (x_lo + 0.25 * (x_hi - x_lo), float(np.median(m[:, 1])), float(np.median(m[:, 2])))
    down = poser.line((g[0], g[1], g[2] + 0.12), g, 30, q0=poser.solve((0.5, 0.02, TABLE_Z + 0.2)))
    caught = None
    for k, v in enumerate(down):
        before = live.snapshot()
        try:
            live.step(v)
        except SimulationDiverged as exc:
            caught = (k, str(exc))
            after = live.snapshot()
            assert after[0] is before[0] and after[2] == before[2]  # not taken
            break
    assert caught is not None and "outside the initial scene's bounding sphere" in caught[1]
    x = live.snapshot()[0].means.double()
    c = m.mean(0)
    assert float((x - torch.as_tensor(c)).norm(dim=1).max()) <= float(np.linalg.norm(m - c, axis=1).max()) + 0.002 + 1e-9
    # the same descent with the check off runs through
    free = load_live(str(untrained_run[0]), str(untrained_run[1]), max_travel_m=0.0)
    for v in down:
        free.step(v)
    assert torch.isfinite(free.snapshot()[0].means).all()


def test_reset_swaps_atomically_and_a_new_count_rebinds(fresh, poser):
    from soma_ros.core.scenes import synthetic_rope

    live = fresh
    vec = poser.solve((0.3, 0.35, TABLE_Z + 0.45))
    for _ in range(3):
        live.step(vec)
    old_state, old_template, _ = live.snapshot()

    # a refused scene changes nothing
    bad = synthetic_rope(500, center=(0.5, 0.0, TABLE_Z))
    bad.means[3, 2] = float("nan")
    with pytest.raises(ValueError, match="non-finite"):
        live.reset(bad)
    assert live.snapshot() == (old_state, old_template, 3)

    # a new scene of another size: rebinds, new positions, steps from 0
    new = synthetic_rope(3000, center=(0.45, 0.05, TABLE_Z), seed=7)
    assert live.reset(new) == 3000
    state, template, steps = live.snapshot()
    assert template is new and steps == 0
    assert live.sim.hierarchy.sizes[0] == 3000
    assert torch.allclose(state.means, new.means, atol=1e-6)
    state, _ = live.step(vec)
    assert state.means.shape == (3000, 3) and torch.allclose(state.means, new.means, atol=1e-6)
    out, cams = live.render(state, new, vec)
    assert out.rgb.shape == (2, 120, 160, 3) and float(out.alpha[0].max()) > 0.5

    # a reset that fails after rebinding leaves the running scene and its binding intact
    sizes = list(live.sim.hierarchy.sizes)
    running = live.snapshot()

    def broken_init_state(*a, **k):
        raise MemoryError("simulated failure in init_state")

    live.sim.init_state = broken_init_state
    try:
        with pytest.raises(MemoryError):
            live.reset(synthetic_rope(1500, center=(0.5, 0.0, TABLE_Z)))
    finally:
        del live.sim.init_state
    assert list(live.sim.hierarchy.sizes) == sizes
    assert live.snapshot() == running
    state, _ = live.step(vec)  # still steps the 3,000-splat scene
    assert state.means.shape == (3000, 3)

    # back to the original count: rebinds again
    assert live.reset(live.bundle.splats) == 2000 and live.sim.hierarchy.sizes[0] == 2000


def test_reset_is_atomic_for_concurrent_steppers_and_readers(fresh, poser):
    """A stepping thread and a reading thread (snapshot, current_splats) run while the
    main thread swaps between scenes of two sizes: readers never see a state of one
    scene with the template of the other, nothing raises."""
    from soma_ros.core.scenes import synthetic_rope

    live = fresh
    vec = poser.solve((0.3, 0.35, TABLE_Z + 0.45))
    scenes = [live.bundle.splats, synthetic_rope(2500, center=(0.5, 0.0, TABLE_Z), seed=3)]
    stop = threading.Event()
    errors: list[BaseException] = []
    counts = {"steps": 0, "reads": 0}

    def stepper():
        try:
            while not stop.is_set():
                live.step(vec)
                counts["steps"] += 1
        except BaseException as exc:  # noqa: BLE001
            errors.append(exc)

    def reader():
        try:
            while not stop.is_set():
                state, template, _ = live.snapshot()
                assert state.means.shape[0] == len(template), (state.means.shape, len(template))
                sp = live.current_splats()
                assert len(sp) == sp.means.shape[0]
                counts["reads"] += 1
        except BaseException as exc:  # noqa: BLE001
            errors.append(exc)

    threads = [threading.Thread(target=stepper), threading.Thread(target=reader)]
    for t in threads:
        t.start()
    try:
        for k in range(6):
            live.reset(scenes[k % 2])
            n0 = counts["steps"]
            deadline = time.monotonic() + 10.0
            while counts["steps"] < n0 + 2 and time.monotonic() < deadline and not errors:
                threads[0].join(0.01)
    finally:
        stop.set()
        for t in threads:
            t.join(30)
    assert not errors, repr(errors[0])
    assert counts["steps"] >= 12 and counts["reads"] > 0


def test_render_fixed_and_mounted_cameras(fresh, poser):
    live = fresh
    state, template, _ = live.snapshot()
    vec = poser.solve((0.5, 0.02, TABLE_Z + 0.25))
    out, cams = live.render(state, template, vec)
    assert out.rgb.shape == (2, 120, 160, 3) and cams.names == ["cam_front", "cam_wrist"]
    front = out.rgb[0]
    assert float((front.sum(-1) > 0.05).float().mean()) > 0.01  # the rope covers part of the image
    assert float(out.depth[0].max()) > 0.3
    # the wrist camera looks down from 25 cm above the rope: it sees it too, and moves with the hand
    assert float((out.rgb[1].sum(-1) > 0.05).float().mean()) > 0.01
    out2, _ = live.render(state, template, poser.solve((0.45, -0.03, TABLE_Z + 0.25), q0=vec))
    assert torch.equal(out2.rgb[0], out.rgb[0]) and not torch.equal(out2.rgb[1], out.rgb[1])
    with pytest.raises(ValueError, match="mounted on 'panda_hand'"):
        live.render(state, template, None)
    with pytest.raises(ValueError, match="unknown camera"):
        LiveSimulator(live.sim, live.bundle, live.robot, camera_names=["nope"])


def test_filter_refuses_positions_outside_the_joint_limits_by_more_than_the_margin():
    f = JointStateFilter(REQUIRED, limits={REQUIRED[0]: (-1.0, 1.0)}, limit_margin=0.05)
    f.push(REQUIRED, _vec(1.04), 100)  # inside the margin: a driver's small overshoot
    for v in (1.06, -1.2, 1e30):
        with pytest.raises(JointStateRejected, match=re.escape(f"1 positions outside the joint limits by more than "
                                                               f"0.05: {REQUIRED[0]} = {v:.4g} (allowed -1.05..1.05)")):
            f.push(REQUIRED, [v] + list(_vec(0.0))[1:], 200)
    assert f.rejected == 3 and np.array_equal(f.sample(), np.array(_vec(1.04)))
    with pytest.raises(ValueError, match="limit_margin"):
        JointStateFilter(REQUIRED, limit_margin=-1.0)


def test_joint_limits_come_from_the_urdf_and_the_gripper_config():
    from soma_ros.core.robot import RobotModel
    from soma_ros.live import joint_limits

    robot = RobotModel.from_config("panda")
    lim = joint_limits(robot, ["panda_joint1", "panda_joint4", "panda_finger_joint1", "not_a_joint"])
    j1 = robot.urdf.joints["panda_joint1"]
    assert lim["panda_joint1"] == (j1.lower, j1.upper) and j1.lower < 0 < j1.upper
    assert set(lim) == {"panda_joint1", "panda_joint4", "panda_finger_joint1"}
    fj = robot.urdf.joints["panda_finger_joint1"]
    assert lim["panda_finger_joint1"] == (fj.lower, fj.upper)
    assert "not_a_joint" not in lim


def test_a_future_stamp_beyond_the_tolerance_does_not_lock_the_stream_out():
    """0.9 s ahead with a 0.1 s tolerance: refused, and the correctly stamped messages that
    follow are all taken (the reference stamp did not move)."""
    f = JointStateFilter(REQUIRED, max_future_s=0.1)
    now = 10**18
    f.push(REQUIRED, _vec(0.0), now, now_ns=now)
    with pytest.raises(JointStateRejected, match="0.900 s ahead"):
        f.push(REQUIRED, _vec(5.0), now + 900_000_000, now_ns=now)
    for i in range(1, 30):
        t = now + i * 33_000_000
        f.push(REQUIRED, _vec(float(i)), t, now_ns=t)
    assert f.rejected == 1 and f.newest_stamp_ns() == now + 29 * 33_000_000


def test_dropped_messages_are_counted_from_sequence_numbers():
    f = JointStateFilter(REQUIRED)
    assert [f.count_sequence(s) for s in (1, 2, 5, 6, 106)] == [0, 0, 2, 0, 99]
    assert f.dropped == 101
    assert f.count_sequence(3) == 0 and f.count_sequence(4) == 0 and f.dropped == 101  # another publisher: afresh
    assert f.count_sequence(None) == 0 and f.count_sequence(0) == 0
