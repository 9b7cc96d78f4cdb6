"""The physics prior (effect ``physics``, soma_ros/core/physics.py) and the terms acting through it."""

from __future__ import annotations

import math

import pytest
import torch

from soma_ros.core.config import ConfigError, EffectSpec, load_model_config
from soma_ros.core.effects import EffectContext, build_effect, build_effects
from soma_ros.core.effects.physics import (PhysicsMods, PhysicsPrior, build_layout, closing_axis, grasp_nodes, grip_time_constant,
                                   pbd_step)
from soma_ros.core.robot import control_point_pattern
from soma_ros.core.robot_config import ControlPointConfig
from soma_ros.core.scenes import synthetic_rope
from soma_ros.core.simulator import RobotAction, SceneContext, Simulator

torch.set_num_threads(1)
UP = torch.tensor([0.0, 0.0, 1.0])
G = torch.tensor([0.0, 0.0, -9.81])
DT = 1.0 / 30.0

def lifted_droop(**params) -> float:
    """mm that a 35 cm bar of 400 splats, grasped at its middle and lifted 20 cm in 1 s and
    held for 0.5 s by the prior alone (48 nodes, 16 substeps, 30 Hz), hangs at its ends below
    its highest node."""
    p = PhysicsPrior.Params(**{"num_nodes": 48, "substeps": 16, **params})
    n, up, gravity, dt = 400, torch.tensor([0.0, 0.0, 1.0]), torch.tensor([0.0, 0.0, -9.81]), 1.0 / 30.0
    pts = torch.zeros(n, 3)
    pts[:, 0] = torch.linspace(0.0, 0.35, n)
    pts[:, 2] = 0.006
    lay = build_layout(pts, torch.full((n,), 0.05 / n), up, torch.tensor(0.0), p)
    c = torch.tensor([0.175, 0.0, 0.006])
    cp = torch.stack([c + torch.tensor([0.0, 0.01, 0.0]), c - torch.tensor([0.0, 0.01, 0.0])])
    coef = PhysicsPrior(p).coefficients()
    x, v, grasp = lay.rest.clone(), torch.zeros(lay.num_nodes, 3), None
    with torch.no_grad():
        for t in range(45):
            cp0 = cp + up * (0.2 * min(t / 30, 1.0))
            cp1 = cp + up * (0.2 * min((t + 1) / 30, 1.0))
            grasp = grasp or grasp_nodes(lay, x, cp0, p)
            x1, grasp = pbd_step(lay, x, v, gravity, up, torch.tensor(0.0), dt, p, coef, cp0, cp1, grasp)
            v, x = (x1 - x) / dt, x1
    ends = x[x[:, 0].argsort()[[0, -1]], 2]
    return 1e3 * float(x[:, 2].max() - ends.mean())



def _params(**kw) -> PhysicsPrior.Params:
    return PhysicsPrior.Params(**{"num_nodes": 24, "substeps": 8, "iterations": 10, **kw})


def _coef(p: PhysicsPrior.Params) -> dict:
    return PhysicsPrior(p).coefficients()


def _chain(n=240, length=0.3, top=0.5, seed=0):
    """Splats of a vertical rope hanging from z = top down to top - length, table at z = 0."""
    g = torch.Generator().manual_seed(seed)
    z = top - torch.rand(n, generator=g) * length
    pts = torch.stack([0.002 * torch.randn(n, generator=g), 0.002 * torch.randn(n, generator=g), z], dim=-1)
    return pts, torch.full((n,), 0.04 / n)


def _sheet(n=400, size=0.2, seed=0):
    """Splats of a flat square cloth lying on the table (z = 0.002)."""
    g = torch.Generator().manual_seed(seed)
    xy = (torch.rand(n, 2, generator=g) - 0.5) * size
    return torch.cat([xy, torch.full((n, 1), 0.002)], dim=-1), torch.full((n,), 0.06 / n)


def _run(lay, p, x, steps, cp=None, closed=False, mods=None, cp_velocity=None, trajectory=False):
    """Node positions after ``steps`` steps of the prior alone (velocities from the positions);
    with ``trajectory`` every step's [steps, K, 3]."""
    coef = _coef(p)
    v = torch.zeros_like(x)
    out = []
    grasp = None
    for _ in range(steps):
        cp0 = cp
        if cp is not None and cp_velocity is not None:
            cp = cp + DT * cp_velocity
        if closed and grasp is None:
            grasp = grasp_nodes(lay, x, cp0, p)
        with torch.no_grad():
            x1, grasp = pbd_step(lay, x, v, G, UP, torch.tensor(0.0), DT, p, coef, cp0, cp, grasp, mods)
        v, x = (x1 - x) / DT, x1
        out.append(x)
    return torch.stack(out) if trajectory else x


def _top_grip(lay):
    """Control points at the chain's top node (two fingers 4 mm apart)."""
    top = lay.rest[lay.rest[:, 2].argmax()]
    return torch.stack([top + torch.tensor([0.0, 0.002, 0.0]), top - torch.tensor([0.0, 0.002, 0.0])])


def test_a_held_rope_hangs_and_a_pressure_wind_swings_it_downwind():
    p = _params()
    pts, m = _chain()
    lay = build_layout(pts, m, UP, torch.tensor(0.0), p)
    cp = _top_grip(lay)
    still = _run(lay, p, lay.rest.clone(), 30, cp, closed=True)
    # held at the top, a vertical rope stays where it hangs: no node moves by more than 5 mm
    assert float((still - lay.rest).norm(dim=-1).max()) < 5e-3
    wind = PhysicsMods(pressure=torch.tensor([0.0, 4.0, 0.0]))
    blown = _run(lay, p, lay.rest.clone(), 40, cp, closed=True, mods=wind, trajectory=True)
    low = lay.rest[:, 2] < lay.rest[:, 2].min() + 0.05  # the free end
    # it swings about a position downwind (a pendulum: the mean over a second, not one instant)
    assert float(blown[10:, low, 1].mean()) > 0.02
    top = lay.rest[:, 2].argmax()
    assert float((blown[:, top] - lay.rest[top]).norm(dim=-1).max()) < 5e-3  # the grip holds the top
    # released (gripper open), the rope falls onto the table and stops above it
    dropped = _run(lay, p, lay.rest.clone(), 20, cp, closed=False)
    assert float(dropped[:, 2].max()) < float(lay.rest[:, 2].max()) - 0.2
    assert float(dropped[:, 2].min()) >= 0.0


def test_a_flat_sheet_on_the_table_feels_no_horizontal_pressure_wind_and_a_uniform_field_is_held_by_friction():
    p = _params()
    pts, m = _sheet()
    lay = build_layout(pts, m, UP, torch.tensor(0.0), p)
    assert lay.sheet
    x = lay.rest.clone()
    v = torch.zeros_like(x)
    coef = _coef(p)
    with torch.no_grad():
        wind = pbd_step(lay, x, v, G, UP, torch.tensor(0.0), DT, p, coef,
                        mods=PhysicsMods(pressure=torch.tensor([5.0, 0.0, 0.0])))[0]
        push = pbd_step(lay, x, v, G, UP, torch.tensor(0.0), DT, p, coef,
                        mods=PhysicsMods(accel=torch.tensor([5.0, 0.0, 0.0])))[0]  # below mu |g| = 9.81
        slide = pbd_step(lay, x, v, G, UP, torch.tensor(0.0), DT, p, coef,
                         mods=PhysicsMods(accel=torch.tensor([5.0, 0.0, 0.0]), friction=torch.tensor(-0.9)))[0]
    assert float((wind - x).norm(dim=-1).max()) < 1e-6
    assert float((push - x).norm(dim=-1).max()) < 1e-6
    assert float((slide - x)[:, 0].mean()) > 1e-3  # a slippery table lets the same field slide it


def test_modifiers_slip_stiffness_and_mass_change_the_held_rope_as_their_names_say():
    p = _params()
    pts, m = _chain()
    lay = build_layout(pts, m, UP, torch.tensor(0.0), p)
    cp = _top_grip(lay)
    up = torch.tensor([0.0, 0.0, 0.3])  # the gripper rises at 0.3 m/s
    ref = _run(lay, p, lay.rest.clone(), 20, cp, True, None, up)
    loose = _run(lay, p, lay.rest.clone(), 20, cp, True, PhysicsMods(grip=torch.tensor(2.5)), up)
    # a loosened grip lets the rope slide down through the fingers: it rises less
    assert float(loose[:, 2].mean()) < float(ref[:, 2].mean()) - 0.01
    # stiffness and mass scale the constraints against the load: a compliant chain hanging from the
    # fingers stretches less when stiffer, more when heavier (compliances large enough that they,
    # not the solve, set the stretch; the table far below, z = -10 m)
    p = _params(bend_compliance=1e-4, stretch_compliance=1e-4)
    lay = build_layout(pts, m, UP, torch.tensor(10.0), p)
    cp = _top_grip(lay)

    def strain(mods):
        x = _run(lay, p, lay.rest.clone(), 30, cp, True, mods)
        d = (x[lay.sj] - x[lay.si]).norm(dim=-1)
        return float(((d - lay.rest_len) / lay.rest_len).mean())

    s0 = strain(None)
    assert s0 > 0.005
    assert strain(PhysicsMods(stiffness=torch.tensor(2.0))) < 0.5 * s0
    assert strain(PhysicsMods(mass=torch.tensor(3.0))) > 2.0 * s0


@pytest.mark.parametrize("solver", [{"bend_compliance": 1e-5},
                                    # the rod's bending compliance is per l^4 (RM identified 30)
                                    {"solver": "newton", "bend_model": "rod", "bend_compliance": 30.0},
                                    {"solver": "newton", "bend_model": "rod", "bend_compliance": 30.0,
                                     "grip_tilt_compliance": 0.002}],
                         ids=["jacobi", "newton_rod", "newton_rod_tilt"])
def test_a_rigidly_held_rope_k_times_heavier_moves_as_one_k_times_softer(solver):
    """Under the hard grip only the ratio of weight to stiffness shapes a held rope (the reference
    world measures a 10x heavier and a 10x softer rope alike), so mass_scale's x k and
    stiffness_scale's x 1/k give the same motion: the hold and its tilt are compliances per unit
    node mass, like the rod's bending. A hold that is not would loosen under a heavier rope, and the
    mass term would droop less than the world's heavier rope."""
    p = _params(stretch_compliance=1e-6, grip_compliance=3e-6, **solver)  # the grip tiny_physics_rod identifies
    pts, m = _chain()
    lay = build_layout(pts, m, UP, torch.tensor(10.0), p)  # the table far below
    cp = _top_grip(lay)
    move = torch.tensor([0.3, 0.0, 0.3])  # the fingers rise and carry it sideways at 0.42 m/s
    base = _run(lay, p, lay.rest.clone(), 20, cp, True, None, move)
    for k in (5.0, 10.0):
        heavy = _run(lay, p, lay.rest.clone(), 20, cp, True, PhysicsMods(mass=torch.tensor(k - 1.0)), move)
        soft = _run(lay, p, lay.rest.clone(), 20, cp, True, PhysicsMods(stiffness=torch.tensor(-math.log(k))), move)
        gap = float((heavy - soft).norm(dim=-1).max())
        effect = float((heavy - base).norm(dim=-1).max())
        assert effect > 0.005, (k, effect)  # the heavier rope does hang differently
        assert gap < 1e-3 * effect, (k, gap, effect)


def _flat_rope(n=240, length=0.36, seed=0):
    """Splats of a straight rope lying on the table along x (z = 0.0065), centred at the origin."""
    g = torch.Generator().manual_seed(seed)
    x = (torch.rand(n, generator=g) - 0.5) * length
    pts = torch.stack([x, 0.002 * torch.randn(n, generator=g), torch.full((n,), 0.0065)], dim=-1)
    return pts, torch.full((n,), 0.04 / n)


def test_a_friction_limited_grip_lets_go_once_the_lifted_load_exceeds_it_and_stays_open():
    """gripper_slip's weaken w: the fingers carry at most e^(-w) of the rope's weight. Lifted at its
    middle, the rope comes off the table as the fingers rise; once the lifted part weighs more, it
    slides out and falls back, earlier the weaker the grip, and is not grasped again while the
    fingers stay closed. w = 0: no limit (bit-identical to no modifier); w < 0: more than the weight,
    which only a heavier rope exceeds."""
    p = _params(num_nodes=32)
    pts, m = _flat_rope()
    lay = build_layout(pts, m, UP, torch.tensor(0.0), p)
    mid = lay.rest[lay.rest[:, 0].abs().argmin()]
    cp = torch.stack([mid + torch.tensor([0.0, 0.002, 0.0]), mid - torch.tensor([0.0, 0.002, 0.0])])
    up = torch.tensor([0.0, 0.0, 0.3])  # 0.3 m/s for 40 steps: 0.4 m, the whole rope off the table

    def top(mods):  # the highest node per step
        return _run(lay, p, lay.rest.clone(), 40, cp, True, mods, up, trajectory=True)[:, :, 2].max(dim=1).values

    hard = top(None)
    assert float(hard[-1]) > 0.35  # the hard grip carries the rope all the way up
    assert torch.equal(top(PhysicsMods(release=torch.tensor(0.0))), hard)
    peaks = {}
    for w in (0.1, 0.7, 2.0):
        z = top(PhysicsMods(release=torch.tensor(w)))
        assert float(z[-1]) < 0.03, (w, z[-1])  # let go: back on the table at the end
        peaks[w] = float(z.max())
    assert peaks[0.1] > peaks[0.7] > peaks[2.0] > 0.02  # a weaker grip lets go lower
    # capacity 1.35 x the nominal weight: the nominal rope is carried, a rope twice as heavy is not
    assert float(top(PhysicsMods(release=torch.tensor(-0.3)))[-1]) > 0.35
    assert float(top(PhysicsMods(release=torch.tensor(-0.3), mass=torch.tensor(1.0)))[-1]) < 0.03
    # the grasp it returns holds nothing, and stays so (the fingers closed): no hold without the modifier either
    coef, x, v = _coef(p), lay.rest.clone(), torch.zeros_like(lay.rest)
    grasp, c0, mods = grasp_nodes(lay, x, cp, p), cp, PhysicsMods(release=torch.tensor(0.7))
    with torch.no_grad():
        for step in range(40):
            c1 = c0 + DT * up
            x1, grasp = pbd_step(lay, x, v, G, UP, torch.tensor(0.0), DT, p, coef, c0, c1, grasp, mods)
            v, x, c0 = (x1 - x) / DT, x1, c1
            if not bool(grasp.held.any()):
                mods = None  # released: from here on a plain hard grip would hold it if it had it
                break
        assert step < 39 and x.shape == lay.rest.shape
        for _ in range(20):
            c1 = c0 + DT * up
            x1, grasp = pbd_step(lay, x, v, G, UP, torch.tensor(0.0), DT, p, coef, c0, c1, grasp, None)
            v, x, c0 = (x1 - x) / DT, x1, c1
    assert not bool(grasp.held.any()) and float(x[:, 2].max()) < 0.03
    with pytest.raises(ConfigError, match="release_d1 > release_d0"):
        PhysicsPrior(_params(release_d0=0.05, release_d1=0.02))


def test_the_table_stops_a_landing_rope_that_starts_a_step_below_its_floor_without_bouncing_it():
    """A rope landing on the table can start a step a little below its floor, moving down (the
    simulator makes the fraction ``gain`` of the prior's velocity change, the network adds its
    own): here 3 mm at 0.4 m/s. The table pushes it back out as a position correction, not a
    velocity: it stays on the table. With ``inelastic_table: false`` the push leaves the first substep at 3 mm / h upwards and the rope jumps 0.16 m, as the
    rope released by a friction-limited grip did in the workflow's rollouts."""
    pts, m = _flat_rope()
    top = {}
    for inelastic in (True, False):
        p = _params(num_nodes=32, substeps=16, inelastic_table=inelastic)
        lay = build_layout(pts, m, UP, torch.tensor(0.0), p)
        coef = _coef(p)
        x = lay.rest - torch.tensor([0.0, 0.0, 0.003])
        v = torch.zeros_like(x)
        v[:, 2] = -0.4
        rise = []
        with torch.no_grad():
            for _ in range(10):
                x1, _ = pbd_step(lay, x, v, G, UP, torch.tensor(0.0), DT, p, coef)
                v, x = (x1 - x) / DT, x1
                rise.append(float((x - lay.rest)[:, 2].max()))
        top[inelastic] = max(rise)
        if inelastic:
            assert abs(rise[-1]) < 1e-5, rise  # on its floor
    assert top[True] < 1e-4 and top[False] > 0.1, top


def _phys_sim(n=600, seed=0, **physics):
    torch.manual_seed(seed)
    cfg = load_model_config("cpu")
    cfg.effects = [EffectSpec.parse(e) for e in (
        "gravity", "support",
        {"name": "physics", "direct": True, "feature": False, "num_nodes": 24, "substeps": 4, "iterations": 6,
         **physics})]
    sim = Simulator(cfg).eval()
    splats = synthetic_rope(n, seed=seed, center=(0.0, 0.0, 0.0))
    return sim, splats


def test_a_compliant_grip_lags_the_fingers_by_its_time_constant_and_stays_stable():
    """gripper_slip's loosen g > 0 holds the grasped nodes by a critically damped spring of time
    constant 0.05 s (e^(2 g) - 1): nearly the hard grip when tau is short (implicit, so even a
    1e-4 s spring is stable), a load that sags further out of the rising fingers the longer tau,
    and a grip that holds nothing when tau is far longer than the carry (the rope falls as if
    released)."""
    assert abs(float(grip_time_constant(torch.tensor(1.0))) - 0.05 * (2.718281828 ** 2 - 1)) < 1e-6
    p = _params()
    pts, m = _chain()
    lay = build_layout(pts, m, UP, torch.tensor(0.0), p)
    cp = _top_grip(lay)
    up = torch.tensor([0.0, 0.0, 0.3])  # the fingers rise at 0.3 m/s for 20 steps (0.2 m)
    fingers = cp.mean(dim=0) + 20 * DT * up

    def run(g):
        mods = None if g is None else PhysicsMods(grip=torch.tensor(g))
        x = _run(lay, p, lay.rest.clone(), 20, cp, True, mods, up, trajectory=True)
        assert bool(torch.isfinite(x).all())
        return x

    hard = run(None)
    held = grasp_nodes(lay, lay.rest, cp, p).held
    gap = {g: float((run(g)[-1, held] - hard[-1, held]).norm(dim=-1).max()) for g in (0.00005, 0.5, 1.0)}
    assert gap[0.00005] < 0.005  # tau = 1e-5 s: the hard grip to 5 mm
    assert gap[0.00005] < gap[0.5] < gap[1.0]  # longer tau: further from the fingers
    soft = run(0.5)[-1, held, 2]
    lag = float((fingers[2] - soft).mean())
    assert 0.02 < lag  # tau 0.086 s: the held end trails the fingers by centimetres
    heavier = PhysicsMods(grip=torch.tensor(0.5), mass=torch.tensor(2.0))
    heavy = _run(lay, p, lay.rest.clone(), 20, cp, True, heavier, up)
    assert float(heavy[held, 2].mean()) < float(soft.mean()) - 0.01  # the same spring, 3x the load: lower
    # tau = 1.6e8 s: holds nothing -- the rope falls as one without a robot does
    free = _run(lay, p, lay.rest.clone(), 20)
    let_go = run(10.0)[-1]
    assert float((let_go - free).norm(dim=-1).max()) < 0.005


def test_in_the_simulator_rest_stays_exactly_at_rest_and_a_grasp_lifts_the_near_end_first():
    sim, splats = _phys_sim()
    scene = SceneContext.table()
    with torch.no_grad():
        s0 = sim.init_state(splats, scene)
        s = s0
        far = RobotAction(torch.tensor([[1.0, 1.0, 0.5], [1.0, 1.01, 0.5]]), 0.0)  # a closed gripper far away
        for a in [None] * 5 + [far] * 5:
            s = sim.step(s, a)
    assert torch.equal(s.means, s0.means)  # bit for bit
    # the prior replaces the passive-object rule
    sim.set_passive_friction(0.5)
    assert sim.effects.physics_host == "physics"
    # a gripper closed on one end of the rope lifts it 8 cm: that end follows, the other end lags
    x0 = splats.means
    end = x0[x0[:, 0].argmin()]
    cp = torch.stack([end + torch.tensor([0.0, 0.004, 0.0]), end - torch.tensor([0.0, 0.004, 0.0])])
    with torch.no_grad():
        s = s0
        for t in range(40):
            lift = torch.tensor([0.0, 0.0, 0.08 * min(t, 30) / 30.0])
            s = sim.step(s, RobotAction(cp + lift, 0.0))
    x = s.means
    near = (x0 - end).norm(dim=-1) < 0.03
    far_end = (x0 - end).norm(dim=-1) > 0.35
    assert float((x[near, 2] - x0[near, 2]).mean()) > 0.05
    assert float((x[far_end, 2] - x0[far_end, 2]).mean()) < 0.5 * float((x[near, 2] - x0[near, 2]).mean())
    assert torch.isfinite(x).all()


def test_a_free_rope_gains_all_of_gravity_per_step_only_from_the_end_velocity():
    """pbd_step's end velocity: a free rope started each step from it falls exactly as semi-implicit
    Euler over all the substeps says (g h^2 N (N + 1) / 2 after N substeps); started from the step's
    mean velocity (x' - x) / dt it gains only about half of g dt per step, and after 10 steps has
    fallen about 60% as far."""
    p = _params()
    pts, m = _chain(top=5.0)  # far above the table
    lay = build_layout(pts, m, UP, torch.tensor(0.0), p)
    coef = {**_coef(p), "damping": torch.tensor(0.0)}
    runs = {}
    for carry in (True, False):
        x, v = lay.rest.clone(), torch.zeros_like(lay.rest)
        with torch.no_grad():
            for _ in range(10):
                x1, _, v_end = pbd_step(lay, x, v, G, UP, torch.tensor(0.0), DT, p, coef, return_velocity=True)
                v, x = (v_end if carry else (x1 - x) / DT), x1
        runs[carry] = float((lay.rest[:, 2] - x[:, 2]).mean())
    n = 10 * p.substeps
    exact = 9.81 * (DT / p.substeps) ** 2 * n * (n + 1) / 2
    assert abs(runs[True] - exact) < 1e-3 * exact  # float32
    assert 0.5 * exact < runs[False] < 0.65 * exact


def test_carry_velocity_lets_a_released_rope_fall_at_the_prior_s_gain_of_gravity():
    """In the simulator: a rope lifted clear of the table and let go falls 0.61x as far as free fall in
    8 steps with the prior starting each step from the splats' mean velocity, 0.84x with
    ``carry_velocity`` (the prior's gain, 0.9, realises 90% of each step's change)."""
    drops = {}
    for carry in (False, True):
        sim, splats = _phys_sim(carry_velocity=carry)
        x0 = splats.means
        end = x0[x0[:, 0].argmin()]
        cp = torch.stack([end + torch.tensor([0.0, 0.004, 0.0]), end - torch.tensor([0.0, 0.004, 0.0])])
        top = torch.tensor([0.0, 0.0, 1.0])
        with torch.no_grad():
            s = sim.init_state(splats, SceneContext.table())
            for t in range(60):
                s = sim.step(s, RobotAction(cp + top * min(t, 40) / 40.0, 0.0))
            assert float(s.means[:, 2].min()) > 0.5  # held clear of the table
            z0 = float(s.means[:, 2].mean())
            for _ in range(8):
                s = sim.step(s, RobotAction(cp + top, 1.0))  # open: let go
        drops[carry] = (z0 - float(s.means[:, 2].mean())) / (0.5 * 9.81 * (8 * DT) ** 2)
    assert drops[False] < 0.7 and 0.78 < drops[True] < 0.95


def test_library_terms_act_through_the_prior_and_as_forces_without_it():
    sim, splats = _phys_sim()
    sim.add_effect({"name": "wind", "direct": True, "accel": [0.0, 3.0, 0.0]})
    sim.add_effect({"name": "stiffness_scale", "direct": True})
    with torch.no_grad():
        s0 = sim.init_state(splats, SceneContext.table())
        ctx = sim.effect_context(s0, None)
        terms = sim.effects.per_term(ctx)
    # through the prior: the wind exerts no force of its own ...
    assert torch.equal(terms["wind"], torch.zeros_like(terms["wind"]))
    assert torch.equal(terms["stiffness_scale"], torch.zeros_like(terms["wind"]))
    # ... and a pressure wind on a rope lying across it, weaker than the table's friction, does not push it
    # along the table (the prior runs: its nodes settle by micrometres)
    f = terms["physics"]
    weight = float((ctx.masses * 9.81).max())
    assert float(f[:, :2].abs().max()) < 1e-6 * weight and float(f[:, 2].abs().max()) < 0.05 * weight
    # without a prior the same term is a force field on every splat, as before
    fx = build_effects([{"name": "wind", "accel": [0.0, 3.0, 0.0]}])
    plain = fx.per_term(ctx)["wind"]
    assert torch.allclose(plain, ctx.masses[:, None] * torch.tensor([0.0, 3.0, 0.0]))
    # unknown solver and bad values are refused in one line
    with pytest.raises(ConfigError, match="substeps"):
        build_effect({"name": "physics", "substeps": 0})
    with pytest.raises(ConfigError, match="gain"):
        build_effect({"name": "physics", "gain": 1.0})
    with pytest.raises(ConfigError, match="form"):
        build_effect({"name": "wind", "form": "gust"})


def test_gradients_reach_an_effect_term_through_the_prior():
    sim, splats = _phys_sim(n=300)
    sim.add_effect({"name": "wind", "direct": True, "form": "field"})
    for p in sim.parameters():
        p.requires_grad_(False)
    sim.effects["wind"].accel.requires_grad_(True)
    s = sim.init_state(splats, SceneContext.table())
    x0 = splats.means
    end = x0[x0[:, 0].argmin()]
    cp = torch.stack([end + torch.tensor([0.0, 0.004, 0.0]), end - torch.tensor([0.0, 0.004, 0.0])])
    for t in range(8):
        s = sim.step(s, RobotAction(cp + torch.tensor([0.0, 0.0, 0.01 * t]), 0.0))
    s.means[:, 1].mean().backward()
    g = sim.effects["wind"].accel.grad
    assert g is not None and torch.isfinite(g).all() and float(g[1]) > 0  # more +y wind, more +y drift


def test_the_live_engine_runs_a_physics_model_exact_at_rest_and_lifts_a_grasped_rope(tmp_path):
    """The live node's engine (no ROS) with a physics-prior model: with the robot far away nothing
    moves, bit for bit; grasped and lifted 10 cm, the splats between the fingers rise with the
    gripper and the rope stays finite."""
    from benchmarks.bench_live import Poser
    from soma_ros.core.checkpoint import save_checkpoint
    from soma_ros.core.scenes import synthetic_bundle
    from soma_ros.live import load_live

    torch.manual_seed(0)
    bundle = synthetic_bundle(2000, seed=0, width=160, height=120)
    cfg = load_model_config("cpu", object="rope")
    cfg.effects = [EffectSpec.parse(e) for e in (
        "gravity", "support", {"name": "physics", "direct": True, "feature": False, "num_nodes": 24, "substeps": 4,
                               "iterations": 6})]
    sim = Simulator(cfg)
    with torch.no_grad():
        sim.init_state(bundle.splats, bundle.scene_context())
    ckpt = save_checkpoint(tmp_path / "checkpoint.pt", sim, extra={"note": "untrained physics prior"})
    live = load_live(str(ckpt), str(bundle.save(tmp_path / "scene")))
    poser = Poser(live.robot, live.base_to_sim.matrix(), live.required_joints, live.bundle.gravity)
    s0 = live.snapshot()[0]
    far = poser.solve((0.3, 0.35, 0.75 + 0.45))
    for k in range(20):
        state, _ = live.step(far if k % 2 else None)
    assert torch.equal(state.means, s0.means)
    m = s0.means
    g = (float(m[:, 0].min()) + 0.05, float(m[:, 1].median()), float(m[:, 2].median()))
    down = poser.line((g[0], g[1], g[2] + 0.1), g, 20, q0=far)
    grip = [poser.with_finger(down[-1], 0.04 - 0.004 * k) for k in range(1, 11)]
    up = poser.line(g, (g[0], g[1], g[2] + 0.1), 30, q0=grip[-1])
    for v in down + grip + [poser.with_finger(u, 0.0) for u in up]:
        state, _ = live.step(v)
    x = state.means
    assert torch.isfinite(x).all()
    near = (m[:, 0] - g[0]).abs() < 0.01
    assert float((x[near, 2] - m[near, 2]).mean()) > 0.05


def test_the_newton_solver_makes_a_stiff_rope_stiff_and_its_bending_compliance_matter():
    """Jacobi passes stop short of the constraints: a stiff rope lifted at its middle droops by
    what the passes allow, and more passes make it stiffer. The Gauss-Newton solve converges in one
    step: its droop is what many passes approach, and the bending compliance then sets it."""
    jac = {it: lifted_droop(iterations=it) for it in (10, 80)}  # mm
    new1 = lifted_droop(solver="newton", newton_iterations=1)
    new3 = lifted_droop(solver="newton", newton_iterations=3)
    assert jac[80] < 0.8 * jac[10]  # the passes, not the compliance, set the Jacobi rope's stiffness
    assert new1 < jac[80] < jac[10]  # the converged rope is stiffer than any of them
    assert abs(new1 - new3) < 2.0  # one Gauss-Newton step per substep has converged
    soft = [lifted_droop(solver="newton", bend_compliance=c) for c in (1e-8, 1e-6, 1e-4)]
    assert soft[0] + 20.0 < soft[1] and soft[1] + 20.0 < soft[2]  # softer bending, lower ends
    assert all(0.0 < d < 200.0 for d in soft)  # hangs, never falls below the table


def test_the_newton_solver_holds_the_grasp_passes_gradients_and_rejects_bad_settings():
    p = _params(solver="newton")
    pts, m = _chain()
    lay = build_layout(pts, m, UP, torch.tensor(0.0), p)
    cp = _top_grip(lay)
    up = torch.tensor([0.0, 0.0, 0.3])
    x = _run(lay, p, lay.rest.clone(), 20, cp, True, None, up)
    top = x[lay.rest[:, 2].argmax()]
    assert abs(float(top[2] - lay.rest[:, 2].max()) - 0.3 * 20 * DT) < 0.005  # the held top rose with the fingers
    d = (x[lay.sj] - x[lay.si]).norm(dim=-1)
    assert float(((d - lay.rest_len) / lay.rest_len).abs().max()) < 0.02  # inextensible
    sim, splats = _phys_sim(n=300, solver="newton")
    sim.add_effect({"name": "wind", "direct": True, "form": "field"})
    for q in sim.parameters():
        q.requires_grad_(False)
    sim.effects["wind"].accel.requires_grad_(True)
    s = sim.init_state(splats, SceneContext.table())
    end = splats.means[splats.means[:, 0].argmin()]
    c2 = torch.stack([end + torch.tensor([0.0, 0.004, 0.0]), end - torch.tensor([0.0, 0.004, 0.0])])
    for t in range(8):
        s = sim.step(s, RobotAction(c2 + torch.tensor([0.0, 0.0, 0.01 * t]), 0.0))
    s.means[:, 1].mean().backward()
    g = sim.effects["wind"].accel.grad
    assert g is not None and torch.isfinite(g).all() and float(g[1]) > 0
    for bad in ({"solver": "gauss"}, {"solver": "newton", "newton_iterations": 0}):
        with pytest.raises(ConfigError, match="solver"):
            PhysicsPrior(_params(**bad))


def test_a_non_finite_state_under_the_newton_solver_is_reported_as_divergence_not_a_linalg_error():
    """A fitted term can blow a rollout up (a negative drag feeds energy in); the workflow scores
    that as a diverged rollout (SimulationDiverged from Simulator.step). The Cholesky factorisation
    of a non-finite system must hand NaN on, not raise mid-step."""
    from soma_ros.core.simulator import SimulationDiverged

    p = _params(solver="newton")
    pts, m = _chain()
    lay = build_layout(pts, m, UP, torch.tensor(0.0), p)
    v = torch.zeros(lay.num_nodes, 3)
    v[3, 0] = float("inf")
    with torch.no_grad():
        x1, _ = pbd_step(lay, lay.rest.clone(), v, G, UP, torch.tensor(0.0), DT, p, _coef(p))
    assert not bool(torch.isfinite(x1).all())
    sim, splats = _phys_sim(n=300, solver="newton")
    sim.add_effect({"name": "quadratic_drag", "direct": True})
    with torch.no_grad():
        sim.effects["quadratic_drag"].coeff.fill_(-1e6)  # feeds energy in until the state overflows
        s = sim.init_state(splats, SceneContext.table())
        end = splats.means[splats.means[:, 0].argmin()]
        cp = torch.stack([end + torch.tensor([0.0, 0.004, 0.0]), end - torch.tensor([0.0, 0.004, 0.0])])
        with pytest.raises(SimulationDiverged):
            for t in range(200):
                s = sim.step(s, RobotAction(cp + torch.tensor([0.0, 0.0, 0.01 * t]), 0.0))


def _pinch(centre_xy, angle, opening, cfg=None):
    """Control points of a gripper pointing straight down with its tips at ``centre_xy`` on the
    table (z = 0), closing along (cos angle, sin angle, 0), laid out by the robot model's pattern."""
    cfg = cfg or ControlPointConfig(count=30, grid=(5, 3), jaw_length=0.018, jaw_width=0.018)
    base, side, c = control_point_pattern(cfg)  # ee frame: closing +y, approach +z
    y_w = torch.tensor([math.cos(angle), math.sin(angle), 0.0], dtype=torch.float64)
    z_w = torch.tensor([0.0, 0.0, -1.0], dtype=torch.float64)
    rot = torch.stack([torch.linalg.cross(y_w, z_w), y_w, z_w], dim=1)  # columns: the ee axes in the world
    local = base + side[:, None] * (opening / 2.0) * c
    origin = torch.tensor([centre_xy[0], centre_xy[1], 0.0], dtype=torch.float64)
    return (local @ rot.T + origin).float(), y_w.float()


def test_the_closing_axis_comes_from_the_jaws_open_or_touching_and_is_none_when_undefined():
    for opening in (0.03, 0.002, 0.0):
        cps, axis = _pinch((0.1, -0.05), 0.6, opening)
        got = closing_axis(cps)
        assert got is not None and abs(float(got @ axis)) > 0.9999, opening
    assert closing_axis(_pinch((0.0, 0.0), 0.6, 0.01)[0][:-1]) is None  # an odd count: no jaw pairs
    line = ControlPointConfig(count=10, grid=(5, 1), jaw_length=0.018, jaw_width=0.0)
    assert closing_axis(_pinch((0.0, 0.0), 0.6, 0.0, line)[0]) is None  # touching jaws of collinear points
    assert closing_axis(_pinch((0.0, 0.0), 0.6, 0.01, line)[0]) is not None  # apart: the line between them


def _rod_params(**kw) -> PhysicsPrior.Params:
    return PhysicsPrior.Params(**{"num_nodes": 40, "substeps": 16, "solver": "newton", "newton_iterations": 1,
                                  "bend_model": "rod", "grip_compliance": 1e-11, **kw})


def _round_rope(n=600, length=0.34, top=0.5, seed=0, arc=0.0):
    """Splats on the surface of a rope 1 cm thick whose centre line runs along x at height ``top``
    (``arc`` > 0: bent in the horizontal plane into a circular arc turning by that many radians)."""
    g = torch.Generator().manual_seed(seed)
    s = torch.rand(n, generator=g) * length
    a = torch.rand(n, generator=g) * 2 * math.pi
    if arc > 0:
        r = length / arc
        centre = torch.stack([r * torch.sin(s / r), r - r * torch.cos(s / r)], dim=-1)
        side = torch.stack([-torch.sin(s / r), torch.cos(s / r)], dim=-1)
    else:
        centre = torch.stack([s, torch.zeros_like(s)], dim=-1)
        side = torch.stack([torch.zeros_like(s), torch.ones_like(s)], dim=-1)
    xy = centre + 0.005 * torch.cos(a)[:, None] * side
    return torch.cat([xy, (top + 0.005 * torch.sin(a))[:, None]], dim=-1), torch.full((n,), 0.04 / n)


def test_the_rod_layout_is_a_chain_along_the_centre_line_of_a_bent_rope():
    pts, m = _round_rope(top=0.0065, arc=2.0)
    lay = build_layout(pts, m, UP, torch.tensor(0.0), _rod_params())
    assert lay.num_nodes == 40 and lay.tri is not None and lay.tri.shape == (3, 38)
    edges = (lay.rest[1:] - lay.rest[:-1]).norm(dim=-1)
    assert float(edges.max()) < 1.6 * float(edges.median())  # consecutive cells are neighbours, no jumps
    r = 0.34 / 2.0  # the arc's radius: the nodes go round it in order, at the rope's centre line
    phi = torch.atan2(lay.rest[:, 0], r - lay.rest[:, 1])
    dphi = phi[1:] - phi[:-1]
    assert bool((dphi > 0).all()) or bool((dphi < 0).all())
    assert float(((lay.rest[:, :2] - torch.tensor([0.0, r])).norm(dim=-1) - r).abs().max()) < 0.004
    assert bool((lay.si + 1 == lay.sj).all()) and not bool(lay.bend.any())  # stretch along the chain only


def test_a_clamped_rod_droops_as_an_euler_bernoulli_cantilever_and_rests_where_it_lies():
    """``bend_compliance`` c of the rod is rho A / (4 EI): a rope clamped at one end droops under its
    own weight by w L^4 / (8 EI) = c g L^4 / 2 while that is small, so linearly in c."""
    pts, m = _round_rope()
    drop = {}
    for c in (0.1, 0.3):
        p = _rod_params(bend_compliance=c, damping=20.0)
        lay = build_layout(pts, m, UP, torch.tensor(0.0), p)
        end = lay.rest[lay.rest[:, 0].argmin()]
        cp = torch.stack([end + torch.tensor([0.01, 0.003, 0.0]), end + torch.tensor([0.01, -0.003, 0.0])])
        x = _run(lay, p, lay.rest.clone(), 150, cp, True)
        held = grasp_nodes(lay, lay.rest, cp, p).held
        tip = int(lay.rest[:, 0].argmax())
        free = float(lay.rest[tip, 0] - lay.rest[held, 0].max())  # the free length beyond the clamp
        drop[c] = float(lay.rest[tip, 2] - x[tip, 2])
        theory = c * 9.81 * free ** 4 / 2
        assert 0.9 * theory < drop[c] < 1.4 * theory, (c, drop[c], theory)
    assert 2.7 < drop[0.3] / drop[0.1] < 3.3  # linear in the compliance
    # a bent rope lying on the table with the fingers near it: its rest shape is its own, nothing moves
    pts, m = _round_rope(top=0.0065, arc=2.0)
    p = _rod_params(bend_compliance=1.0)
    lay = build_layout(pts, m, UP, torch.tensor(0.0), p)
    cp = lay.rest[:2] + torch.tensor([0.0, 0.0, 0.03])
    x = _run(lay, p, lay.rest.clone(), 10, cp)
    assert float((x - lay.rest).abs().max()) < 1e-6


def test_a_tilting_grip_turns_the_held_section_about_the_closing_axis_as_a_rotational_spring():
    """``grip_tilt_compliance`` t: the held section turns about the fingers' closing axis on a spring
    of stiffness node mass / t, so a stiff rod held near one end tilts by its arm's weight torque
    over that stiffness (linearly in t while small); without it (t = 0) the section stays level.
    The rope's splats lie on its centre line: on a rope of jittered cells the rod's bending, whose
    rest shape turns with the smallest rotation of each chord, resists a turn that twists a chord
    about itself, which a rod as stiff as this one (c 0.01) feels as much as the hinge."""
    s = torch.rand(600, generator=torch.Generator().manual_seed(0)) * 0.34
    pts, m = torch.stack([s, torch.zeros_like(s), torch.full_like(s, 0.5)], dim=-1), torch.full((600,), 0.04 / 600)
    tilt = {}
    for t in (0.0, 1e-3, 3e-3):
        p = _rod_params(bend_compliance=1e-2, damping=20.0, grip_tilt_compliance=t)
        prior = PhysicsPrior(p)
        assert ("tilt" in prior.coefficients()) == (t > 0)
        lay = build_layout(pts, m, UP, torch.tensor(0.0), p)
        end = lay.rest[lay.rest[:, 0].argmin()]
        cp = torch.stack([end + torch.tensor([0.01, 0.003, 0.0]), end + torch.tensor([0.01, -0.003, 0.0])])
        x = _run(lay, p, lay.rest.clone(), 150, cp, True)
        g = grasp_nodes(lay, lay.rest, cp, p)
        assert int(g.held.sum()) >= 2
        axis = closing_axis(cp)
        # the held section's turn about the closing axis (y): its end nodes' slope, the far one lower
        held = x[g.held]
        d = held[-1] - held[0] if float(held[-1, 0]) > float(held[0, 0]) else held[0] - held[-1]
        tilt[t] = math.atan2(-float(d[2]), float(d[0]))
        if t > 0:
            torque = 9.81 * float((lay.node_mass * (lay.rest[:, 0] - cp.mean(dim=0)[0])).sum())
            theory = torque / (float(lay.node_mass.mean()) / t)  # small angles, a rigid arm
            assert 0.8 * theory < tilt[t] < 1.25 * theory, (t, tilt[t], theory)
        assert abs(float(axis[1])) > 0.999
    assert abs(tilt[0.0]) < 0.005  # the hard grip: the section stays as it was grasped
    assert 2.6 < tilt[3e-3] / tilt[1e-3] < 3.2  # linear in the compliance
    with pytest.raises(ConfigError, match="grip_tilt_compliance"):
        PhysicsPrior(_params(grip_tilt_compliance=1e-3))  # the Jacobi passes have no hinge
    with pytest.raises(ConfigError, match="grip_tilt_compliance"):
        PhysicsPrior(_rod_params(grip_tilt_compliance=-1.0))


def test_the_rod_bending_model_needs_the_newton_solver_and_a_known_name():
    with pytest.raises(ConfigError, match="bend_model"):
        PhysicsPrior(_rod_params(bend_model="beam"))
    with pytest.raises(ConfigError, match="newton"):
        PhysicsPrior(_rod_params(solver="jacobi"))


def test_a_gripper_closing_between_sparse_nodes_holds_the_cells_of_the_splats_between_its_fingers():
    # a 30 x 30 cm sheet of 900 splats on 9 nodes (spacing ~10 cm): no node centre within the
    # 2 cm attach radius of a grip between two of them, yet the fingers close on the sheet
    p = PhysicsPrior.Params(num_nodes=9)
    g = torch.linspace(0.0, 0.3, 30)
    pts = torch.stack(torch.meshgrid(g, g, indexing="ij"), dim=-1).reshape(-1, 2)
    pts = torch.cat([pts, torch.full((pts.shape[0], 1), 0.002)], dim=1)
    lay = build_layout(pts, torch.full((pts.shape[0],), 0.1 / pts.shape[0]), UP, torch.tensor(0.0), p)
    d = torch.cdist(lay.rest, lay.rest)
    d.fill_diagonal_(math.inf)
    i, j = divmod(int(d.argmin()), lay.num_nodes)
    c = 0.5 * (lay.rest[i] + lay.rest[j])  # halfway between two neighbouring nodes, on the sheet
    c[2] = 0.002
    cp = torch.stack([c + torch.tensor([0.0, 0.0, 0.004]), c - torch.tensor([0.0, 0.0, 0.004])])
    assert float((lay.rest - c).norm(dim=-1).min()) > p.attach_radius
    assert grasp_nodes(lay, lay.rest, cp, p) is None  # node centres alone: the fingers hold nothing
    grasp = grasp_nodes(lay, lay.rest, cp, p, pts)
    near = (pts - c).norm(dim=-1) <= p.attach_radius
    assert grasp is not None and bool(near.any())
    assert set(torch.nonzero(grasp.held).flatten().tolist()) == set(lay.node_of[near].tolist())
    # a node within reach keeps the node rule: the same grasp with or without the splats
    c2 = lay.rest[i].clone()
    cp2 = torch.stack([c2 + torch.tensor([0.0, 0.0, 0.004]), c2 - torch.tensor([0.0, 0.0, 0.004])])
    assert torch.equal(grasp_nodes(lay, lay.rest, cp2, p).held, grasp_nodes(lay, lay.rest, cp2, p, pts).held)
    # nothing within reach of either: no grasp
    far = cp + torch.tensor([0.0, 0.0, 0.5])
    assert grasp_nodes(lay, lay.rest, far, p, pts) is None
