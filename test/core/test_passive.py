"""The passive-object rule (DynamicsConfig.passive_friction, soma_ros.core.simulator)."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from soma_ros.core.config import ConfigError, EffectSpec, load_model_config
from soma_ros.core.effects import EffectContext, build_effects
from soma_ros.core.scenes import synthetic_rope
from soma_ros.core.simulator import RobotAction, SceneContext, Simulator

torch.set_num_threads(1)
G_DT = 9.81 / 30.0  # |g| dt of SceneContext.table()


def _sim(mu, n=600, seed=0):
    torch.manual_seed(seed)
    cfg = load_model_config("cpu")
    cfg.dynamics.passive_friction = mu
    sim = Simulator(cfg).eval()
    with torch.no_grad():
        s0 = sim.init_state(synthetic_rope(n, seed=seed, center=(0.0, 0.0, 0.0)), SceneContext.table())
    return sim, s0


def _lifted(state, dz):
    return dataclasses.replace(state, positions=[p + torch.tensor([0.0, 0.0, dz]) for p in state.positions])


def test_velocity_limits_by_hand():
    """Hand-computed cases of the rule on the root velocity (z up, table at z = 0, mu = 0.5)."""
    sim, s0 = _sim(0.5)
    air = _lifted(s0, 0.05)  # off the table: no friction
    v = lambda *x: torch.tensor([x], dtype=torch.float32)  # noqa: E731
    pr = sim._passive_root
    # horizontal speed may not grow: 0.632 m/s capped to the previous 0.5, direction kept
    out = pr(v(0.5, 0, 0), v(0.6, 0.2, 0), None, air)
    assert torch.allclose(out, v(0.6, 0.2, 0) * 0.5 / (0.6 ** 2 + 0.2 ** 2) ** 0.5, atol=1e-6)
    # slowing down and falling are the network's: unchanged
    assert torch.equal(pr(v(0.5, 0, 0), v(0.1, 0, -0.3), None, air), v(0.1, 0, -0.3))
    # upward speed: at most max(previous, 0)
    assert torch.allclose(pr(v(0, 0, -0.2), v(0, 0, 0.1), None, air), v(0, 0, 0))
    assert torch.allclose(pr(v(0, 0, 0.2), v(0, 0, 0.3), None, air), v(0, 0, 0.2))
    # on the table: Coulomb friction takes mu |g| dt = 0.1635 m/s off the horizontal speed
    out = pr(v(0.5, 0, 0), v(0.6, 0, 0), None, s0)
    assert torch.allclose(out, v(0.5 - 0.5 * G_DT, 0, 0), atol=1e-6)
    assert torch.equal(pr(v(0.1, 0, 0), v(0.1, 0, 0), None, s0), v(0, 0, 0))  # stops, no reversal
    # direct effects act after the cap and before friction: a push weaker than mu |g| moves nothing,
    # a stronger one accelerates by the excess
    assert torch.equal(pr(v(0, 0, 0), v(0, 0, 0), v(4.0, 0, 0), s0), v(0, 0, 0))
    out = pr(v(0, 0, 0), v(0, 0, 0), v(9.0, 0, 0), s0)
    assert torch.allclose(out, v((9.0 - 0.5 * 9.81) / 30.0, 0, 0), atol=1e-6)
    assert torch.allclose(pr(v(0, 0, 0), v(0, 0, 0), v(0, 0, 3.0), air), v(0, 0, 0.1), atol=1e-6)  # lift: direct
    # untouched (no non-reference force at all): a rising object slows down at least at |g|
    assert torch.allclose(pr(v(0, 0, 0.5), v(0, 0, 0.5), None, air, untouched=True), v(0, 0, 0.5 - G_DT), atol=1e-6)
    assert torch.equal(pr(v(0, 0, 0.2), v(0, 0, 0.3), None, air, untouched=True), v(0, 0, 0))
    # on the table the support stops motion into it: every splat at its resting height (f = 1)
    assert torch.equal(pr(v(0, 0, 0), v(0, 0, -0.3), None, s0), v(0, 0, 0))
    assert torch.allclose(pr(v(0, 0, 0), v(0, 0, 0), v(0, 0, -9.0), s0), v(0, 0, 0))  # a gripper pressing down
    # ... partly: a fraction f of the mass at its resting height keeps (1 - f) of the downward speed
    h0 = s0.positions[0][:, 2]
    low = h0 < torch.quantile(h0, 0.25)  # the lowest quarter stays, the rest is 5 cm up
    part = dataclasses.replace(s0, positions=[torch.where(low[:, None], s0.positions[0],
                                                          s0.positions[0] + torch.tensor([0.0, 0.0, 0.05]))]
                               + list(s0.positions[1:]))
    f = float((s0.episode.masses[0] * low).sum() / s0.episode.masses[0].sum())
    assert torch.allclose(pr(v(0, 0, 0), v(0, 0, -0.3), None, part), v(0, 0, -0.3 * (1 - f)), atol=1e-6)
    # an object sunk into the table is pushed back up by half its depth below resting - contact per
    # step, at most at |g| dt: 1.5 cm -> 0.5 * 0.005 * 30 m/s; 4 cm -> |g| dt
    assert torch.allclose(pr(v(0, 0, 0), v(0, 0, -0.1), None, _lifted(s0, -0.015)), v(0, 0, 0.5 * 0.005 * 30), atol=1e-5)
    assert torch.allclose(pr(v(0, 0, 0), v(0, 0, -0.1), None, _lifted(s0, -0.04)), v(0, 0, G_DT), atol=1e-5)


def test_untouched_slide_stops_and_rest_is_kept_exactly():
    """A random-weight model, its object given a 0.3 m/s horizontal slide with the robot far away:
    without the rule it keeps going; with it the horizontal speed never grows and the slide
    stops within ceil(0.3 / (mu |g| dt)) steps. At rest, the rule changes nothing (bit for bit)."""
    far = RobotAction(torch.tensor([[2.0, 2.0, 0.5]]), 1.0)
    outs = {}
    for mu in (None, 0.5):
        sim, s0 = _sim(mu)
        with torch.no_grad():
            rest = sim.rollout(s0, [far] * 20)[-1]
            assert torch.equal(rest.means, s0.means)  # the rest fixed point, with the rule on too
            L = sim.hierarchy.root_level
            push = torch.tensor([[0.3 * s0.episode.scene.dt, 0.0, 0.0]])
            s = dataclasses.replace(s0, resid_prev=[r if l != L else r - push for l, r in enumerate(s0.resid)])
            speeds = []
            for _ in range(40):
                prev_resid = s.resid[L]
                s = sim.step(s, far)
                speeds.append(float((s.resid[L] - prev_resid)[0, :2].norm()) / s0.episode.scene.dt)
        outs[mu] = (speeds, float((s.positions[L] - s0.positions[L]).norm()))
    free, held = outs[None], outs[0.5]
    assert free[0][-1] > 0.1 and free[1] > 0.3  # the network alone lets it slide on
    assert all(b <= a + 1e-6 for a, b in zip([0.3] + held[0], held[0]))
    assert held[0][1] == 0.0 and held[1] < 0.02  # 0.3 - 2 x 0.1635 < 0: at rest after two steps


def test_which_forces_act():
    es = build_effects(["gravity", "support", {"name": "wind", "direct": True, "accel": [1.0, 0.0, 0.0]},
                        {"name": "linear_drag", "coeff": 0.5}])
    x = synthetic_rope(200, seed=1, center=(0.0, 0.0, 0.0)).means
    ctx = lambda v: EffectContext(positions=x, velocities=v, masses=torch.full((200,), 1e-4),  # noqa: E731
                                  attrs=torch.zeros(200, 0), gravity=torch.tensor([0.0, 0.0, -9.81]),
                                  plane_normal=torch.tensor([0.0, 0.0, 1.0]), plane_offset=torch.tensor(0.0),
                                  dt=1 / 30)
    total, direct, acting = es.split_active(ctx(torch.zeros_like(x)))
    assert acting == 1 and direct is not None  # direct wind, and a drag at zero speed: passive, not untouched
    assert es.split_active(ctx(torch.ones_like(x)))[2] == 2  # a moving object feels the (feature) drag
    assert es.split_active(ctx(torch.zeros_like(x)), check_active=False)[2] == 2
    calm = build_effects(["gravity", "support", {"name": "wind", "direct": True}])  # zero wind
    assert calm.split_active(ctx(torch.zeros_like(x)))[2] == 0
    t2, d2 = es.split(ctx(torch.zeros_like(x)))
    assert torch.equal(t2, total) and torch.equal(d2, direct)
    # an exempt direct term (DynamicsConfig.passive_exempt) makes the step active; forces unchanged
    t3, d3, acting3 = es.split_active(ctx(torch.zeros_like(x)), exempt=["wind"])
    assert acting3 == 2 and torch.equal(t3, total) and torch.equal(d3, direct)
    assert calm.split_active(ctx(torch.zeros_like(x)), exempt=["wind"])[2] == 0  # zero force: still untouched


def test_an_exempt_direct_term_is_not_braked_by_the_rule():
    """A direct push of 3 m/s^2 (below mu |g| = 4.9) on the resting object: under the rule its root
    does not move; with the term exempt (a term the model was trained with) the step is not passive and
    the object moves as without the rule, bit for bit. Unknown keys are refused."""
    far = RobotAction(torch.tensor([[2.0, 2.0, 0.5]]), 1.0)
    moved = {}
    for mu, exempt in ((None, None), (0.5, None), (0.5, ["push"])):
        sim, s0 = _sim(mu)
        sim.add_effect({"name": "wind", "key": "push", "direct": True, "accel": [3.0, 0.0, 0.0]})
        sim.set_passive_friction(mu, exempt)
        with torch.no_grad():
            s0 = sim.init_state(synthetic_rope(600, seed=0, center=(0.0, 0.0, 0.0)), SceneContext.table())
            end = sim.rollout(s0, [far] * 10)[-1]
            L = sim.hierarchy.root_level
            moved[(mu, bool(exempt))] = (end.positions[L] - s0.positions[L], end.means - s0.means)
    assert float(moved[(None, False)][0][0, 0]) > 0.01  # the root slides downwind
    assert float(moved[(0.5, False)][0][0, :2].abs().max()) == 0.0  # the rule holds the root in the plane
    assert all(torch.equal(a, b) for a, b in zip(moved[(0.5, True)], moved[(None, False)]))
    with pytest.raises(ValueError, match="no effect 'nope'"):
        sim.set_passive_friction(0.5, ["nope"])


def test_the_exemption_can_hold_only_while_the_gripper_is_closed():
    """``passive_exempt_closed``: the exempt push acts unbraked with the gripper closed (bit for bit
    as without the rule) and is held by the rule with it open, or with no robot at all."""
    ends = {}
    for mu, closed, grip in ((None, False, 0.0), (0.5, False, 1.0), (0.5, True, 0.0), (0.5, True, 1.0), (0.5, True, None)):
        sim, _ = _sim(mu)
        sim.add_effect({"name": "wind", "key": "push", "direct": True, "accel": [3.0, 0.0, 0.0]})
        sim.set_passive_friction(mu, ["push"], closed)
        assert sim.config.dynamics.passive_exempt_closed is closed
        assert sim.config.dynamics.passive_rule_text() == (
            "off" if mu is None else f"friction 0.5, not on steps where push acts{' with the gripper closed' * closed}")
        action = None if grip is None else RobotAction(torch.tensor([[2.0, 2.0, 0.5]]), grip)
        with torch.no_grad():
            s0 = sim.init_state(synthetic_rope(600, seed=0, center=(0.0, 0.0, 0.0)), SceneContext.table())
            ends[(mu, closed, grip)] = sim.rollout(s0, [action] * 10)[-1].positions[sim.hierarchy.root_level] - \
                s0.positions[sim.hierarchy.root_level]
    free = ends[(None, False, 0.0)]
    assert float(free[0, 0]) > 0.01
    assert torch.equal(ends[(0.5, False, 1.0)], free)  # exempt whatever the gripper: unbraked
    assert torch.equal(ends[(0.5, True, 0.0)], free)  # closed: exempt
    assert float(ends[(0.5, True, 1.0)][0, :2].abs().max()) == 0.0  # open: the rule holds the root
    assert float(ends[(0.5, True, None)][0, :2].abs().max()) == 0.0  # no robot: the rule holds the root


def test_config_validation_and_checkpoint_default():
    cfg = load_model_config("cpu")
    assert cfg.dynamics.passive_friction is None  # training and evaluation configs: off
    cfg.dynamics.passive_friction = -0.1
    with pytest.raises(ConfigError, match="passive_friction"):
        cfg.dynamics.validate()
    cfg.dynamics.passive_friction = 0.5
    cfg.dynamics.passive_contact_m = 0.0
    with pytest.raises(ConfigError, match="passive_contact_m"):
        cfg.dynamics.validate()
    cfg.dynamics.passive_contact_m = 0.01
    cfg.dynamics.passive_exempt = ["robot", ""]
    with pytest.raises(ConfigError, match="passive_exempt"):
        cfg.dynamics.validate()
    with pytest.raises(ConfigError, match="fitted_after_training"):
        EffectSpec.parse({"name": "wind", "fitted_after_training": "yes"})
    cfg.dynamics.passive_exempt = ["robot"]
    cfg.dynamics.passive_exempt_closed = "yes"
    with pytest.raises(ConfigError, match="passive_exempt_closed"):
        cfg.dynamics.validate()


def test_an_open_gripper_in_reach_does_not_hold_a_rising_object_up():
    """The rule's "nothing holds it up" covers an open gripper within reach: its coupling only
    drags, so an object rising at 0.3 m/s slows down at least at |g| (the root's upward speed after
    one step <= max(0.3 - |g| dt, 0) + the open coupling's share), while a closed grip may keep it rising
    (the cap is then max(previous, 0)). Before, an open gripper left in reach after a release let a
    rising rope keep its speed: the live rope crept up 0.05-0.15 m over a 300-step hold."""
    torch.manual_seed(0)
    cfg = load_model_config({**load_model_config("cpu").to_dict(), "effects": [
        {"name": "gravity"}, {"name": "support", "tau": 0.01, "gain": 1.0, "stiffness": 500.0},
        {"name": "robot", "radius": 0.05, "max_neighbors": 64, "hidden": 32, "layers": 1, "form": "coupling",
         "prior_grip": 0.5, "prior_open": 0.02, "direct": True, "feature": False}]})
    cfg.dynamics.passive_friction = 0.5
    sim = Simulator(cfg).eval()
    with torch.no_grad():
        s0 = sim.init_state(synthetic_rope(600, seed=0, center=(0.0, 0.0, 0.0)), SceneContext.table())
    L = sim.hierarchy.root_level
    up = _lifted(s0, 0.05)
    rise = torch.tensor([[0.0, 0.0, 0.3 * s0.episode.scene.dt]])
    up = dataclasses.replace(up, resid_prev=[r if l != L else r - rise for l, r in enumerate(up.resid)])
    x = up.means
    cp = (x[x[:, 0].argmax()] + torch.tensor([0.0, 0.0, 0.02]))[None]  # a finger 2 cm above one end
    speeds = {}
    for grip in (1.0, 0.0):
        act = RobotAction(cp, grip)
        with torch.no_grad():
            assert sim.effects.split_active(sim.effect_context(up, act))[2] == 1  # in reach: direct force only
            nxt = sim.step(up, act)
        speeds[grip] = float((nxt.resid[L] - up.resid[L])[0, 2]) / s0.episode.scene.dt
    assert speeds[1.0] <= max(0.3 - G_DT, 0.0) + 0.01
    assert speeds[0.0] > speeds[1.0] + 0.2
