"""Effect registry and the built-in force terms."""

from __future__ import annotations

import copy
from dataclasses import dataclass

import pytest
import torch

from soma_ros.core.config import ConfigError, EffectSpec, load_model_config
from soma_ros.core.effects import (
    EFFECTS,
    Effect,
    EffectContext,
    build_effect,
    build_effects,
    known_effects,
    register_effect,
)
from soma_ros.core.scenes import synthetic_rope
from soma_ros.core.simulator import RobotAction, SceneContext, Simulator

torch.set_num_threads(1)


def _ctx(n=50, z=None, vel=None, cp=None, cpv=None, grip=0.5, seed=0) -> EffectContext:
    g = torch.Generator().manual_seed(seed)
    pos = torch.rand(n, 3, generator=g) * 0.1
    if z is not None:
        pos[:, 2] = z
    return EffectContext(
        positions=pos,
        velocities=torch.zeros(n, 3) if vel is None else vel,
        masses=torch.full((n,), 0.01),
        attrs=torch.zeros(n, 5),
        gravity=torch.tensor([0.0, 0.0, -9.81]),
        plane_normal=torch.tensor([0.0, 0.0, 1.0]),
        plane_offset=torch.tensor(0.0),
        dt=1 / 30,
        control_points=cp,
        control_velocities=None if cp is None else (torch.zeros_like(cp) if cpv is None else cpv),
        gripper=None if cp is None else torch.tensor(grip),
    )


def test_registry_lists_builtins_and_unknown_names_fail_clearly():
    for name in ("gravity", "support", "robot", "wind", "linear_drag", "quadratic_drag"):
        assert name in EFFECTS
    with pytest.raises(ConfigError) as exc:
        build_effect("tornado")
    msg = str(exc.value)
    assert "tornado" in msg and all(n in msg for n in known_effects())
    with pytest.raises(ConfigError, match=r"unknown key.*known: accel"):
        build_effect({"name": "wind", "acel": [1, 0, 0]})
    with pytest.raises(ConfigError, match="duplicate"):
        load_model_config({"effects": ["gravity", "gravity"]})
    # two instances of one effect need distinct keys
    s = build_effects(["wind", {"name": "wind", "key": "gust", "accel": [0.0, 1.0, 0.0]}])
    assert s.keys() == ["wind", "gust"]
    with pytest.raises(ConfigError, match="already present"):
        s.add("wind")


def test_gravity_support_and_drag_formulas():
    tau = 0.01
    ctx = _ctx(z=torch.linspace(-0.005, 0.02, 50))
    m = ctx.masses[:, None]
    assert torch.allclose(build_effect("gravity")(ctx), m * torch.tensor([0.0, 0.0, -9.81]))
    sup = build_effect({"name": "support", "tau": tau, "stiffness": 400.0})(ctx)
    z = ctx.positions[:, 2]
    assert torch.all(sup[:, :2] == 0)
    assert torch.all(sup[z >= tau] == 0)  # no support beyond tau
    # at or below the plane: carries the full weight, plus the penetration penalty
    below = z <= 0
    expect = 0.01 * (9.81 + 400.0 * (-z[below]))
    assert torch.allclose(sup[below, 2], expect, rtol=1e-5)
    mid = (z > 0) & (z < tau)
    assert bool(((sup[mid, 2] > 0) & (sup[mid, 2] < 0.01 * 9.81)).all())  # smooth falloff
    # drags
    v = torch.randn(50, 3)
    ctx = _ctx(vel=v)
    lin = build_effect({"name": "linear_drag", "coeff": 0.5})(ctx)
    assert torch.allclose(lin, -0.5 * ctx.masses[:, None] * v)
    quad = build_effect({"name": "quadratic_drag", "coeff": 2.0})(ctx)
    assert torch.allclose(quad, -2.0 * ctx.masses[:, None] * v.norm(dim=-1, keepdim=True) * v, atol=1e-6)
    # fresh wind / drags add exactly nothing
    for name in ("wind", "linear_drag", "quadratic_drag"):
        assert torch.count_nonzero(build_effect(name)(ctx)) == 0


def test_robot_force_is_local_smooth_and_learnable():
    torch.manual_seed(0)
    eff = build_effect({"name": "robot", "radius": 0.05, "hidden": 16}, attr_dim=5)
    far = torch.tensor([[5.0, 5.0, 5.0]])
    assert torch.count_nonzero(eff(_ctx(cp=far))) == 0
    assert torch.count_nonzero(build_effects(["robot"], attr_dim=5)(_ctx())) == 0  # no robot at all
    ctx = _ctx(cp=torch.tensor([[0.05, 0.05, 0.05]]), cpv=torch.tensor([[0.1, 0.0, 0.0]]))
    f = eff(ctx)
    d = (ctx.positions - ctx.control_points).norm(dim=-1)
    assert torch.count_nonzero(f[d >= 0.05]) == 0
    assert bool((f[d < 0.05].norm(dim=-1) > 0).all())
    # gripper state and control-point velocity are inputs
    ctx2 = _ctx(cp=ctx.control_points, cpv=ctx.control_velocities, grip=1.0)
    assert not torch.allclose(eff(ctx2), f)
    # continuity at the radius: a splat just inside gets an almost-zero force
    one = EffectContext(
        positions=torch.tensor([[0.0499, 0.0, 0.0], [0.01, 0.0, 0.0]]), velocities=torch.zeros(2, 3),
        masses=torch.full((2,), 0.01), attrs=torch.zeros(2, 5), gravity=torch.tensor([0.0, 0.0, -9.81]),
        plane_normal=torch.tensor([0.0, 0.0, 1.0]), plane_offset=torch.tensor(0.0), dt=1 / 30,
        control_points=torch.zeros(1, 3), control_velocities=torch.zeros(1, 3), gripper=torch.tensor(0.0),
    )
    f1 = eff(one).detach()
    assert float(f1[0].norm()) < 1e-3 * float(f1[1].norm())
    # the per-control-point cap keeps the nearest splats within the radius (dense objects)
    capped = build_effect({"name": "robot", "radius": 0.08, "max_neighbors": 5, "hidden": 8}, attr_dim=5)
    cps = torch.tensor([[0.05, 0.05, 0.05], [0.0, 0.0, 0.0]])
    ctx3 = _ctx(n=300, cp=cps)
    j, i = capped.edges(ctx3)
    d = torch.cdist(cps, ctx3.positions)
    for p in range(2):
        near = torch.sort(d[p]).indices[:5]
        expect = set(near[d[p][near] < 0.08].tolist())
        assert set(i[j == p].tolist()) == expect and len(expect) >= 1
    assert torch.count_nonzero(capped(ctx3).norm(dim=-1)) == len(set(i.tolist()))
    # gradients reach all its parameters
    f.square().sum().backward()
    for n, p in eff.named_parameters():
        assert p.grad is not None and p.grad.abs().max() > 0, n


def _rotz(a: float) -> torch.Tensor:
    c, s = torch.cos(torch.tensor(a)), torch.sin(torch.tensor(a))
    return torch.tensor([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def test_robot_coupling_form_is_physical_invariant_and_learnable():
    torch.manual_seed(0)
    spec = {"name": "robot", "radius": 0.05, "hidden": 16, "form": "coupling", "prior_grip": 0.25}
    eff = build_effect(spec, attr_dim=5)
    cp = torch.tensor([[0.05, 0.05, 0.05]])
    # a motionless control point and splats at rest: only the push/pull along u (finger -> splat)
    ctx = _ctx(cp=cp, grip=0.0)
    f = eff(ctx).detach()
    u = ctx.positions - cp
    inside = u.norm(dim=-1) < 0.05
    assert bool(inside.sum() >= 3) and torch.count_nonzero(f[~inside]) == 0
    cross = torch.linalg.cross(f[inside], u[inside])
    assert float(cross.norm(dim=-1).max()) < 1e-6 * max(1e-12, float(f.norm(dim=-1).max())) + 1e-12
    # with the push head at zero, a control point moving at v drags the splats at rest: a = w k v / dt
    with torch.no_grad():
        eff.coef_mlp[-1].weight[1].zero_()
        eff.coef_mlp[-1].bias[1].zero_()
        eff.coef_mlp[-1].weight[0].zero_()  # k = prior_grip everywhere
    v = torch.tensor([[0.0, 0.0, 0.3]])
    ctx = _ctx(cp=cp, cpv=v, grip=0.0)
    a = eff(ctx).detach() / ctx.masses[:, None]
    d = (ctx.positions - cp).norm(dim=-1)
    w = (1 - (d / 0.05) ** 2).clamp_min(0) ** 2
    expect = w[:, None] * 0.25 * v / (1 / 30)
    assert torch.allclose(a, expect, atol=1e-5)
    # a splat already moving with the control point feels nothing from it (no preferred world direction)
    ctx = _ctx(cp=cp, cpv=v, vel=v.expand(50, 3).clone(), grip=0.0)
    assert float(eff(ctx).detach().abs().max()) < 1e-7
    # rotation invariance: rotating the scene rotates the force (fresh, untrained weights)
    torch.manual_seed(1)
    eff = build_effect(spec, attr_dim=5)
    g = torch.Generator().manual_seed(3)
    vel = torch.randn(50, 3, generator=g) * 0.1
    cpv = torch.tensor([[0.1, -0.2, 0.05]])
    c1 = _ctx(cp=cp, cpv=cpv, vel=vel)
    R = _rotz(0.7) @ torch.tensor([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
    c2 = _ctx(cp=cp @ R.T, cpv=cpv @ R.T, vel=vel @ R.T)
    c2.positions = c1.positions @ R.T
    assert torch.allclose(eff(c2), eff(c1) @ R.T, atol=1e-7)
    # bounded: per splat at most (|dv| / dt + accel_scale) x mass, however many control points
    many = _ctx(cp=torch.rand(30, 3) * 0.1, cpv=torch.ones(30, 3) * 0.2, grip=0.0)
    amax = (eff(many) / many.masses[:, None]).norm(dim=-1).max().detach()
    assert float(amax) <= 0.2 * 3 ** 0.5 * 30 + 9.81 + 1e-4
    # gradients reach every parameter; bad parameters fail clearly
    eff(c1).square().sum().backward()
    for n, p in eff.named_parameters():
        assert p.grad is not None and p.grad.abs().max() > 0, n
    with pytest.raises(ConfigError, match="form"):
        build_effect({"name": "robot", "form": "spring"})
    with pytest.raises(ConfigError, match="prior_grip"):
        build_effect({"name": "robot", "form": "coupling", "prior_grip": 1.0})


def test_robot_coupling_carry_moves_the_rest_of_the_object_with_the_grasp():
    """``carry``: a'_i = a_i + (1 - omega_i) phi s (u_G - v_bar) / dt, hand-computed on a lift."""
    torch.manual_seed(0)
    spec = {"name": "robot", "radius": 0.05, "hidden": 16, "form": "coupling", "prior_grip": 0.5, "carry": 0.6}
    eff = build_effect(spec, attr_dim=5)
    plain = build_effect({k: v for k, v in spec.items() if k != "carry"}, attr_dim=5)
    plain.load_state_dict({k: v for k, v in eff.state_dict().items() if k != "carry_logit"})
    cp = torch.tensor([[0.02, 0.02, 0.02], [0.03, 0.02, 0.02]])
    v = torch.tensor([[0.0, 0.0, 0.3], [0.0, 0.0, 0.2]])
    g = torch.Generator().manual_seed(4)
    for grip in (0.0, 0.4):
        vel = torch.randn(200, 3, generator=g) * 0.05
        ctx = _ctx(n=200, cp=cp, cpv=v, vel=vel, grip=grip)
        a = eff(ctx).detach() / ctx.masses[:, None]
        a0 = plain(ctx).detach() / ctx.masses[:, None]  # the coupling without the carry
        w = (1 - (torch.cdist(ctx.positions, cp) / 0.05) ** 2).clamp_min(0) ** 2  # [N, P]
        wsum = w.sum(1)
        omega = wsum.clamp_max(1.0) * (1.0 - grip)
        cpv_i = (w @ v) / wsum.clamp_min(1e-30)[:, None]
        u_g = (omega[:, None] * cpv_i).sum(0) / omega.sum()  # equal masses
        A = 0.6 * omega.max() * (u_g - vel.mean(0)) * 30
        expect = a0 + (1.0 - omega)[:, None] * A
        assert torch.allclose(a, expect, atol=1e-4)
        far = wsum == 0
        assert bool(far.sum() > 10) and float(a[far, 2].min()) > 0  # the splats out of reach rise too
    # dissipative: an object already moving with the grasp feels no carry; a closed, motionless
    # gripper brings a moving object towards rest (no drift)
    same = _ctx(n=200, cp=cp, cpv=v[:1].expand(2, 3).clone(), vel=v[:1].expand(200, 3).clone(), grip=0.0)
    assert torch.allclose(eff(same), plain(same), atol=1e-6)
    drift = torch.tensor([0.1, 0.0, 0.0]).expand(200, 3).clone()
    still = _ctx(n=200, cp=cp, cpv=torch.zeros(2, 3), vel=drift, grip=0.0)
    extra = (eff(still) - plain(still)).detach() / still.masses[:, None]
    assert float(extra[:, 0].max()) <= 0 < -float(extra[:, 0].min()) and float(extra[:, 1:].abs().max()) < 1e-6
    assert float((extra[:, 0] / 30).min()) >= -0.1 - 1e-6  # never more than the relative velocity
    # gripper open: exactly the plain coupling; nothing in reach: exactly zero
    ctx = _ctx(n=200, cp=cp, cpv=v, grip=1.0)
    assert torch.equal(eff(ctx), plain(ctx))
    ctx = _ctx(n=200, cp=torch.tensor([[1.0, 1.0, 1.0]]), cpv=v[:1], grip=0.0)
    assert float(eff(ctx).abs().max()) == 0.0
    # phi is learned: gradients reach it
    eff(_ctx(n=200, cp=cp, cpv=v, grip=0.0)).square().sum().backward()
    assert eff.carry_logit.grad is not None and float(eff.carry_logit.grad.abs()) > 0
    with pytest.raises(ConfigError, match="carry"):
        build_effect({"name": "robot", "form": "coupling", "carry": 1.0})
    with pytest.raises(ConfigError, match="carry"):
        build_effect({"name": "robot", "form": "mlp", "carry": 0.5})


def test_effects_declared_zero_at_rest_are_exactly_zero_at_rest():
    """``zero_at_rest`` lets the trainer skip the frames before contact; it must hold exactly,
    whatever the (learnable) parameters."""
    flagged = [n for n in known_effects() if EFFECTS[n].zero_at_rest]
    assert {"linear_drag", "quadratic_drag", "table_friction"} <= set(flagged)
    params = {"linear_drag": {"coeff": 0.7}, "quadratic_drag": {"coeff": -0.3}, "table_friction": {"mu": 0.6}}
    for name in flagged:
        eff = build_effect({"name": name, **params.get(name, {})}, attr_dim=5)
        at_rest = _ctx(z=0.002)  # on the table, in the contact band, velocities exactly 0
        assert torch.count_nonzero(eff(at_rest)) == 0, name
        moving = _ctx(z=0.002, vel=torch.full((50, 3), 0.1))
        assert torch.count_nonzero(eff(moving)) > 0, name
    from soma_ros.training.train import rest_reach

    cfg = load_model_config("cpu")
    cfg.effects.append(EffectSpec("table_friction", key="friction", params={"mu": 0.5}, direct=True, feature=False))
    assert rest_reach(Simulator(cfg)) == pytest.approx(0.05 + 0.01)
    cfg.effects.append(EffectSpec("wind"))
    assert rest_reach(Simulator(cfg)) is None  # wind acts at rest


def test_trainable_false_freezes_and_custom_effects_register():
    eff = build_effect({"name": "wind", "trainable": False, "accel": [1.0, 0.0, 0.0]})
    assert not any(p.requires_grad for p in eff.parameters())

    @register_effect("test_spring_to_origin")
    class Spring(Effect):
        @dataclass
        class Params:
            k: float = 1.0

        def forward(self, ctx):
            return -self.params.k * ctx.masses[:, None] * ctx.positions

    try:
        s = build_effects(["gravity", {"name": "test_spring_to_origin", "k": 3.0}])
        ctx = _ctx()
        assert torch.allclose(s.per_term(ctx)["test_spring_to_origin"], -3.0 * 0.01 * ctx.positions)
        with pytest.raises(ValueError, match="already registered"):
            register_effect("test_spring_to_origin")(type("Other", (Spring,), {}))
    finally:
        EFFECTS.pop("test_spring_to_origin", None)


def test_wind_onset_switches_the_field_on_mid_episode():
    """A wind with onset T: no force and exactly the windless motion before T - rise, the full field
    from T on, a C1 ramp between; time = steps x dt."""
    sp = synthetic_rope(400, seed=4)
    scene = SceneContext.table()
    torch.manual_seed(0)
    sim = Simulator(load_model_config("cpu")).eval()
    gust = sim.add_effect({"name": "wind", "accel": [0.0, 3.0, 0.0], "onset": 0.2, "rise": 0.1})
    still = copy.deepcopy(sim)
    with torch.no_grad():
        still.effects["wind"].accel.zero_()
    dt = scene.dt
    with torch.no_grad():
        s, q = sim.init_state(sp, scene), still.init_state(sp, scene)
        far = RobotAction(torch.full((30, 3), 3.0), 0.0)
        for k in range(int(round(0.35 / dt))):
            t = k * dt
            ctx = sim.effect_context(s, far)
            assert ctx.time == pytest.approx(t)
            g = float(gust.gate(ctx))
            if t <= 0.1 + 1e-9:
                assert g == 0.0 and torch.equal(s.means, q.means)  # before the ramp: the windless motion exactly
            elif t >= 0.2 - 1e-9:
                assert g == 1.0
            else:
                assert 0.0 < g < 1.0
            f = gust(ctx)
            assert torch.allclose(f, ctx.masses[:, None] * torch.tensor([0.0, 3.0 * g, 0.0]))
            s, q = sim.step(s, far), still.step(q, far)
    assert float((s.means - q.means).norm(dim=-1).max()) > 1e-6  # and then it blows
    # a negative onset or a rise <= 0 is refused
    with pytest.raises(ConfigError, match="onset"):
        build_effect({"name": "wind", "onset": -1.0})
    with pytest.raises(ConfigError, match="rise"):
        build_effect({"name": "wind", "rise": 0.0})


def test_adding_wind_by_config_changes_force_and_motion():
    sp = synthetic_rope(800, seed=3)
    scene = SceneContext.table()
    base = load_model_config("cpu")
    torch.manual_seed(0)
    sim = Simulator(base).eval()
    windy_cfg = load_model_config("cpu")
    windy_cfg.effects.append(EffectSpec("wind", params={"accel": [2.0, 0.0, 0.0]}))
    torch.manual_seed(0)
    windy = Simulator(windy_cfg).eval()
    windy.load_state_dict(sim.state_dict(), strict=False)
    with torch.no_grad():
        s0 = sim.init_state(sp, scene)
        w0 = windy.init_state(sp, scene)
        f_base, f_wind = sim.forces(s0, None), windy.forces(w0, None)
        assert torch.allclose(f_wind - f_base, w0.episode.masses[0][:, None] * torch.tensor([2.0, 0.0, 0.0]))
        far = RobotAction(torch.full((30, 3), 3.0), 0.0)
        a = sim.rollout(s0, [far] * 5)[-1]
        b = windy.rollout(w0, [far] * 5)[-1]
    assert torch.equal(a.means, s0.means)  # no wind: at rest
    assert float((b.means - w0.means).norm(dim=-1).max()) > 1e-6  # wind moves it
    # add_effect on a live model: zero-initialised wind changes nothing until fitted
    eff = sim.add_effect({"name": "wind"})
    assert "wind" in sim.effects and sim.config.effects[-1].name == "wind"
    assert [p is eff.accel for p in sim.effect_parameters("wind")] == [True]
    with torch.no_grad():
        s1 = sim.init_state(sp, scene)
        assert torch.equal(sim.rollout(s1, [far] * 3)[-1].means, s1.means)


# ----------------------------------------------------------------------------- direct effects (residual physics)
def _still_network(sim: Simulator) -> Simulator:
    """Zero the network's last decoder layer (no bias): its outputs are exactly 0 whatever the
    inputs, so only the direct pathway can move the object."""
    with torch.no_grad():
        sim.gnn.decoder.last.weight.zero_()
    return sim


def _far() -> RobotAction:
    return RobotAction(torch.full((30, 3), 3.0), 1.0)


def test_direct_spec_parses_roundtrips_and_is_refused_for_reference_effects():
    s = EffectSpec.parse({"name": "wind", "direct": True, "accel": [1.0, 0.0, 0.0]})
    assert s.direct and s.params == {"accel": [1.0, 0.0, 0.0]}
    assert s.to_yaml_dict() == {"name": "wind", "direct": True, "accel": [1.0, 0.0, 0.0]}
    assert EffectSpec.parse(s.to_yaml_dict()) == s
    plain = EffectSpec.parse({"name": "wind"})
    assert plain.direct is False and "direct" not in plain.to_yaml_dict()  # old configs unchanged
    with pytest.raises(ConfigError, match="direct: expected bool"):
        EffectSpec.parse({"name": "wind", "direct": "yes"})
    for name in ("gravity", "support"):
        with pytest.raises(ConfigError, match="cannot be direct"):
            build_effect({"name": name, "direct": True})
    es = build_effects(["gravity", {"name": "wind", "direct": True, "accel": [1.0, 0.0, 0.0]},
                        {"name": "linear_drag", "key": "drag", "coeff": 0.5}])
    assert es.direct_keys == ["wind"]
    ctx = _ctx(vel=torch.randn(50, 3))
    total, direct = es.split(ctx)
    assert torch.equal(total, es(ctx))
    assert torch.allclose(direct, ctx.masses[:, None] * torch.tensor([1.0, 0.0, 0.0]))
    assert build_effects(["gravity", "wind"]).split(ctx)[1] is None
    # feature: false -- integrated, but not in the force the network sees
    hidden = EffectSpec.parse({"name": "wind", "direct": True, "feature": False, "accel": [1.0, 0.0, 0.0]})
    assert hidden.to_yaml_dict() == {"name": "wind", "direct": True, "feature": False, "accel": [1.0, 0.0, 0.0]}
    assert EffectSpec.parse(hidden.to_yaml_dict()) == hidden and "feature" not in s.to_yaml_dict()
    es2 = build_effects(["gravity", hidden, {"name": "linear_drag", "key": "drag", "coeff": 0.5}])
    seen, direct2 = es2.split(ctx)
    assert torch.equal(seen, es2["gravity"](ctx) + es2["drag"](ctx))
    assert torch.equal(direct2, direct) and not torch.equal(seen, es2(ctx))
    with pytest.raises(ConfigError, match="feature: false must be direct"):
        EffectSpec.parse({"name": "wind", "feature": False})
    with pytest.raises(ConfigError, match="feature: expected bool"):
        EffectSpec.parse({"name": "wind", "direct": True, "feature": "no"})


def test_uniform_direct_wind_translates_rigidly_by_the_discrete_closed_form():
    """Semi-implicit Euler on the root's residual: v_n = n a dt, d_n = a dt^2 n (n + 1) / 2
    (-> 1/2 a (n dt)^2 as dt -> 0); every lower level gets a's excess over its parent's = 0,
    so all splats move by d_n (float rounding only); the covariances do not change."""
    torch.manual_seed(0)
    sp = synthetic_rope(800, seed=3)
    scene = SceneContext.table()
    cfg = load_model_config("cpu")
    a = torch.tensor([1.0, -0.5, 0.0])
    cfg.effects.append(EffectSpec("wind", params={"accel": a.tolist()}, direct=True))
    sim = _still_network(Simulator(cfg).eval())
    n, dt = 20, scene.dt
    with torch.no_grad():
        s0 = sim.init_state(sp, scene)
        last = sim.rollout(s0, [_far()] * n)[-1]
    disp = last.means - s0.means
    expect = a * dt * dt * n * (n + 1) / 2
    assert torch.allclose(disp, expect.expand_as(disp), rtol=0, atol=1e-5 * float(expect.norm()))
    cont = 0.5 * a * (n * dt) ** 2  # the continuous form differs by (n + 1) / n: 5% here
    assert float((disp.mean(0) - cont).norm()) > 0.04 * float(cont.norm())
    assert torch.allclose(last.covs, s0.covs, atol=1e-12)
    # the same wind as a feature only does not move this network at all (the pathway it lacked)
    cfg2 = load_model_config("cpu")
    cfg2.effects.append(EffectSpec("wind", params={"accel": a.tolist()}))
    feat = Simulator(cfg2).eval()
    feat.load_state_dict(sim.state_dict(), strict=False)
    with torch.no_grad():
        f0 = feat.init_state(sp, scene)
        assert torch.equal(feat.rollout(f0, [_far()] * 3)[-1].means, f0.means)


def test_direct_force_on_some_splats_moves_them_relative_to_the_rest():
    torch.manual_seed(0)
    sp = synthetic_rope(800, seed=3)
    scene = SceneContext.table()
    sim = _still_network(Simulator(load_model_config("cpu")).eval())
    sim.add_effect({"name": "mass_scale", "direct": True, "excess": 1.0})  # extra weight above 5 cm only
    end = sp.means[sp.means[:, 0].argmax()].clone()
    near = (sp.means - end).norm(dim=-1) < 0.01
    far = (sp.means - end).norm(dim=-1) > 0.2
    sp.means[near, 2] += 0.1  # one end of the rope held up (the initial state is the rest state)
    with torch.no_grad():
        s0 = sim.init_state(sp, scene)
        last = sim.rollout(s0, [None] * 10)[-1]
    disp = (last.means - s0.means)[:, 2]
    assert float(disp[near].mean()) < -1e-3  # the raised end sags under its extra load...
    assert float(disp[far].abs().max()) < 0.1 * float(disp[near].abs().mean())  # ...the far end barely moves


def test_without_a_splat_head_splats_follow_their_fine_cluster_rigidly():
    """A direct force that shears every fine cluster (each splat pushed up in proportion to its offset
    along the rope from its cluster's centre) moves the clusters relative to each other, while the
    splats of a model without a splat head keep their offsets to their fine cluster."""
    torch.manual_seed(0)
    sp = synthetic_rope(800, seed=3)
    scene = SceneContext.table()

    @register_effect("test_shear")
    class Shear(Effect):
        @dataclass
        class Params:
            k: float = 2.0  # 1/s^2 per m along the rope

        def forward(self, ctx):
            x = ctx.positions
            return self.params.k * ctx.masses[:, None] * torch.stack(
                [torch.zeros_like(x[:, 0]), torch.zeros_like(x[:, 0]), x[:, 0] - x[:, 0].mean()], 1)

    try:
        cfg = load_model_config("cpu")
        cfg.effects.append(EffectSpec("test_shear", direct=True))
        torch.manual_seed(1)
        sim = _still_network(Simulator(cfg).eval())
        with torch.no_grad():
            s0 = sim.init_state(sp, scene)
            last, parent = sim.rollout(s0, [_far()] * 8)[-1], sim.hierarchy.parents[0]
    finally:
        EFFECTS.pop("test_shear", None)
    m = sp.mass[:, None]
    k = int(parent.max()) + 1

    def centres(x):
        return torch.zeros(k, 3).index_add_(0, parent, m * x) / torch.zeros(k, 1).index_add_(0, parent, m)

    def offsets(x):  # each splat's offset from its cluster's centre of mass
        return x - centres(x)[parent]

    moved = (last.means - s0.means).norm(dim=-1)
    assert float(moved.max()) > 1e-3  # the shear moves the rope (its clusters, relative to each other)
    assert float((offsets(last.means) - offsets(s0.means)).abs().max()) < 1e-6  # rigid fine clusters


@pytest.mark.parametrize("model", ["cpu", "paper"])
def test_zero_force_direct_effects_are_a_bitwise_noop(model):
    """Random weights, robot pushing: adding every library candidate as a direct effect at its
    zero initialisation gives the same rollout bit for bit (and the rest state stays put)."""
    torch.manual_seed(4)
    sp = synthetic_rope(600, seed=1, center=(0.0, 0.0, 0.0))
    scene = SceneContext.table()
    sim = Simulator(load_model_config(model)).eval()
    cp0 = sp.means[sp.means[:, 0] > 0.15].mean(0) + 0.005 * torch.randn(30, 3)
    push = [RobotAction(cp0 + torch.tensor([0.0, 0.003 * i, 0.002 * i]), 0.0) for i in range(6)]
    steps = 6 if model == "cpu" else 3
    with torch.no_grad():
        s0 = sim.init_state(sp, scene)
        ref = sim.rollout(s0, push[:steps])
        rest = sim.rollout(s0, [_far()] * 3)[-1]
    assert float((ref[-1].means - s0.means).abs().max()) > 1e-6  # not vacuous: the robot moves it
    for name in ("wind", "linear_drag", "quadratic_drag", "table_friction", "gripper_slip", "mass_scale"):
        sim.add_effect({"name": name, "direct": True})
    assert len(sim.effects.direct_keys) == 6
    with torch.no_grad():
        s1 = sim.init_state(sp, scene)
        got = sim.rollout(s1, push[:steps])
        rest1 = sim.rollout(s1, [_far()] * 3)[-1]
    for a, b in zip(ref, got):
        assert torch.equal(a.means, b.means) and torch.equal(a.covs, b.covs) and torch.equal(a.quats, b.quats)
    assert torch.equal(rest1.means, s1.means) and torch.equal(rest.means, rest1.means)


def test_direct_forces_are_differentiable_and_checkpoints_keep_the_flag(tmp_path):
    from soma_ros.core.checkpoint import load_checkpoint, save_checkpoint

    torch.manual_seed(0)
    sp = synthetic_rope(500, seed=2)
    scene = SceneContext.table()
    sim = _still_network(Simulator(load_model_config("cpu")).eval())
    sim.add_effect({"name": "wind", "direct": True})
    n, dt = 6, scene.dt
    s0 = sim.init_state(sp, scene)
    last = sim.rollout(s0, [_far()] * n)[-1]
    last.means[:, 0].sum().backward()
    g = sim.effects["wind"].accel.grad
    # the network is inert here, so the whole gradient is the direct pathway's: N dt^2 n (n+1) / 2
    assert g is not None and torch.allclose(g, torch.tensor([len(sp) * dt * dt * n * (n + 1) / 2, 0.0, 0.0]),
                                            rtol=1e-4, atol=1e-4)
    # a trainable random network: the gradient reaches the direct term too
    sim2 = Simulator(load_model_config("cpu")).eval()
    sim2.add_effect({"name": "table_friction", "direct": True, "mu": 0.3})
    sim2.add_effect({"name": "wind", "direct": True, "accel": [0.5, 0.0, 0.0]})
    s0 = sim2.init_state(sp, scene)
    loss = sim2.rollout(s0, [_far()] * 4)[-1].means.square().sum()
    loss.backward()
    for k in ("wind", "table_friction"):
        for p in sim2.effect_parameters(k):
            assert p.grad is not None and torch.isfinite(p.grad).all() and float(p.grad.abs().sum()) > 0, k
    # checkpoint round trip keeps the flag and the behaviour
    with torch.no_grad():
        sim2.effects["wind"].accel.copy_(torch.tensor([0.3, 0.1, 0.0]))
    save_checkpoint(tmp_path / "c.pt", sim2)
    back = load_checkpoint(tmp_path / "c.pt").eval()
    assert back.effects.direct_keys == ["table_friction", "wind"]
    assert [e.direct for e in back.config.effects] == [False, False, False, True, True]
    with torch.no_grad():
        a = sim2.rollout(sim2.init_state(sp, scene), [_far()] * 3)[-1].means
        b = back.rollout(back.init_state(sp, scene), [_far()] * 3)[-1].means
    assert torch.equal(a, b)
