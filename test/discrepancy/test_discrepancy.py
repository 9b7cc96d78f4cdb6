"""Discrepancy workflow (issue #8): the new effect terms (zero at init, direction of force),
the statistics that name a winner, and the workflow end to end on tiny effect-free data
(mechanics, report schema, negative control)."""

from __future__ import annotations

import dataclasses
import json
import math
import shutil

import numpy as np
import pytest
import torch

from soma_ros.core.effects import EffectContext, build_effect
from soma_ros.discrepancy.workflow import bootstrap_explained, decide, load_discrepancy_config

torch.set_num_threads(1)

G = torch.tensor([0.0, 0.0, -9.81])
N = torch.tensor([0.0, 0.0, 1.0])


def _ctx(pos, vel, cp=None, cpv=None, grip=None):
    n = pos.shape[0]
    return EffectContext(
        positions=pos, velocities=vel, masses=torch.full((n,), 0.01), attrs=torch.zeros(n, 0), gravity=G,
        plane_normal=N, plane_offset=torch.tensor(0.0), dt=1 / 30,
        control_points=cp, control_velocities=cpv, gripper=None if grip is None else torch.tensor(grip))


def _random_ctx(seed=0, robot=True):
    g = torch.Generator().manual_seed(seed)
    pos = torch.rand(50, 3, generator=g) * torch.tensor([0.3, 0.3, 0.1])
    vel = torch.randn(50, 3, generator=g) * 0.2
    cp = pos[:3] + 0.005
    return _ctx(pos, vel, cp, torch.randn(3, 3, generator=g) * 0.1, 0.0) if robot else _ctx(pos, vel)


@pytest.mark.parametrize("name", ["table_friction", "gripper_slip", "mass_scale"])
def test_new_terms_are_zero_at_init_and_fit_through_gradients(name):
    eff = build_effect({"name": name})
    ctx = _random_ctx()
    f = eff(ctx)
    assert f.shape == (50, 3) and torch.count_nonzero(f) == 0
    # a gradient reaches the parameters (so the workflow can fit them)
    for p in eff.parameters():
        with torch.no_grad():
            p.fill_(0.3)
    eff(ctx).pow(2).sum().backward()
    # (a parameter that acts only through a physics prior, gripper_slip's loosen, has none here)
    assert all(p.grad is not None and float(p.grad.abs().sum()) > 0 for _, p in eff.acting_parameters(False))


def test_table_friction_opposes_tangential_velocity_only_in_contact():
    eff = build_effect({"name": "table_friction", "params": {"mu": 0.5}})
    pos = torch.tensor([[0.0, 0.0, 0.002], [0.1, 0.0, 0.002], [0.2, 0.0, 0.1]])
    vel = torch.tensor([[0.3, -0.2, 0.0], [0.0, 0.0, 0.4], [0.3, 0.0, 0.0]])
    f = eff(_ctx(pos, vel)).detach()
    assert float(f[0] @ vel[0]) < 0 and abs(float(f[0, 2])) < 1e-9  # opposes sliding, tangential
    assert torch.allclose(f[1], torch.zeros(3), atol=1e-9)  # normal motion: no friction
    assert torch.allclose(f[2], torch.zeros(3))  # above the contact band
    # Coulomb magnitude mu m g (w ~ 1 at 2 mm, speed >> v_eps)
    assert abs(float(f[0].norm()) - 0.5 * 0.01 * 9.81) < 0.1 * 0.5 * 0.01 * 9.81
    # signed: mu < 0 pushes along the velocity (a table more slippery than the model believes)
    eff2 = build_effect({"name": "table_friction", "params": {"mu": -0.5}})
    assert float(eff2(_ctx(pos, vel)).detach()[0] @ vel[0]) > 0


def test_gripper_slip_acts_on_the_held_object_as_a_whole_only_when_closed():
    pos = torch.tensor([[0.0, 0.0, 0.05], [0.2, 0.0, 0.05], [0.3, 0.0, 0.05]])
    vel = torch.tensor([[0.0, 0.0, 0.0], [0.0, 0.0, 0.3], [0.0, 0.0, 0.3]])  # v_bar = (0, 0, 0.2)
    cp, cpv = torch.tensor([[0.0, 0.0, 0.05]]), torch.tensor([[0.0, 0.0, 0.5]])
    ctx = _ctx(pos, vel, cp, cpv, 0.0)
    # hold: every splat, the far ones too, gets hold s (u_G - v_bar) / dt; s = 1 at the control point
    f = build_effect({"name": "gripper_slip", "params": {"hold": 0.2}})(ctx)
    want = 0.01 * 0.2 * (0.5 - 0.2) * 30.0
    torch.testing.assert_close(f, torch.tensor([0.0, 0.0, want]).expand(3, 3))
    slip = build_effect({"name": "gripper_slip", "params": {"hold": -0.2}})(ctx)
    assert float(slip[2, 2].detach()) < 0  # < 0: the object lags the lifting gripper
    # sag: the held object slides down, s-weighted (half closed: s = 0.5)
    sag = build_effect({"name": "gripper_slip", "params": {"sag": 0.5}})(_ctx(pos, vel, cp, cpv, 0.5))
    torch.testing.assert_close(sag, (0.01 * 0.5 * 0.5 * G).expand(3, 3))
    eff = build_effect({"name": "gripper_slip", "params": {"hold": 2.0, "sag": 0.5}})
    assert torch.count_nonzero(eff(_ctx(pos, vel, cp, cpv, 1.0))) == 0  # gripper open: nothing held
    assert torch.count_nonzero(eff(_ctx(pos, vel, cp + 1.0, cpv, 0.0))) == 0  # closed, nothing in reach
    assert torch.count_nonzero(eff(_ctx(pos, vel))) == 0  # no robot


def test_mass_scale_weighs_only_lifted_material():
    eff = build_effect({"name": "mass_scale", "params": {"excess": 1.0}})
    pos = torch.tensor([[0.0, 0.0, 0.005], [0.0, 0.0, 0.2]])
    f = eff(_ctx(pos, torch.zeros(2, 3)))
    assert torch.allclose(f[0], torch.zeros(3))
    torch.testing.assert_close(f[1], 0.01 * G)


def test_decide_names_a_clear_winner_and_refuses_noise():
    rng = np.random.default_rng(0)
    base = [1.0 + 0.1 * rng.random(15) for _ in range(4)]
    good = [b * (0.5 + 0.1 * rng.standard_normal(15)) for b in base]  # explains about half
    noise = [b * (1 + 0.05 * rng.standard_normal(15)) for b in base]
    s = bootstrap_explained(base, {"good": good, "noise": noise}, 400, seed=1)
    ex = {"good": float(1 - sum(x.sum() for x in good) / sum(x.sum() for x in base)), "noise": float(1 - sum(x.sum() for x in noise) / sum(x.sum() for x in base))}
    named, rows, info = decide(ex, s, 0.05, 0.1)
    assert named == "good" and rows[0]["name"] == "good" and info["significant"]
    assert 0.3 < rows[0]["ci_low"] < ex["good"] < rows[0]["ci_high"] < 0.7
    named, _, info = decide({"noise": ex["noise"]}, {"noise": s["noise"]}, 0.05, 0.1)
    assert named == "none" and not info["significant"]
    # two candidates explaining the same: no significant margin -> none
    s2 = bootstrap_explained(base, {"a": good, "b": [g * 1.0 for g in good]}, 300, seed=2)
    assert decide({"a": ex["good"], "b": ex["good"]}, s2, 0.05, 0.1)[0] == "none"


def test_the_wrist_load_breaks_a_tie_the_camera_cannot():
    """Two candidates move the object alike (a heavier and a softer rope: the same 3D residual);
    only one also explains the wrist load. With the load channel it is named; without, neither
    is. The load never lifts a candidate over the 3D floor: the gap to close is the motion's."""
    rng = np.random.default_rng(5)
    base = [1.0 + 0.1 * rng.random(15) for _ in range(5)]
    kin = [b * (0.5 + 0.05 * rng.standard_normal(15)) for b in base]  # both explain about half of the motion
    s = bootstrap_explained(base, {"heavy": kin, "soft": [k.copy() for k in kin]}, 400, seed=1)
    ex = {k: float(1 - sum(x.sum() for x in kin) / sum(x.sum() for x in base)) for k in ("heavy", "soft")}
    assert decide(ex, s, 0.05, 0.1)[0] == "none"  # a tie on the camera's evidence
    lbase = [0.3 + 0.05 * rng.random(15) for _ in range(5)]  # |load error| of the unchanged model, N
    lheavy = [0.2 * b for b in lbase]
    lsoft = [b * (1.0 + 0.02 * rng.standard_normal(15)) for b in lbase]
    ls = bootstrap_explained(lbase, {"heavy": lheavy, "soft": lsoft}, 400, seed=1)
    lex = {"heavy": 0.8, "soft": float(1 - sum(x.sum() for x in lsoft) / sum(x.sum() for x in lbase))}
    named, rows, info = decide(ex, s, 0.05, 0.1, lex, ls)
    assert named == "heavy" and info["wrist_load"] and info["significant"] and info["margin_lower_bound"] > 0.5
    assert rows[0]["score"] == pytest.approx(ex["heavy"] + 0.8) and rows[1]["name"] == "soft"
    # a load explained far below -1 counts as -1 in the score
    named, rows, _ = decide(ex, s, 0.05, 0.1, {"heavy": 0.8, "soft": -7.0},
                            {"heavy": ls["heavy"], "soft": ls["soft"] - 8.0})
    assert rows[1]["score"] == pytest.approx(ex["soft"] - 1.0) and rows[1]["load_ci_low"] == -1.0
    # the load alone names nothing: a term that explains the load but not the motion stays below the floor
    flat = [b * (1 + 0.02 * rng.standard_normal(15)) for b in base]
    s3 = bootstrap_explained(base, {"heavy": flat}, 300, seed=2)
    e3 = {"heavy": float(1 - sum(x.sum() for x in flat) / sum(x.sum() for x in base))}
    assert decide(e3, s3, 0.05, 0.1, {"heavy": 0.8}, {"heavy": ls["heavy"][:300]})[0] == "none"


def test_predicted_load_weighs_the_lifted_part_on_a_closed_gripper():
    from soma_ros.core.effects import EffectSet
    from soma_ros.core.simulator import SceneContext
    from soma_ros.discrepancy.workflow import predicted_load

    class Model:  # what predicted_load reads of a Simulator: its effects
        effects = EffectSet([])

    scene = SceneContext(G, N, -0.75, 1 / 30)
    m = torch.full((10,), 0.004)  # 40 g
    x = torch.zeros(10, 3)
    x[:, 2] = 0.75 + 0.005  # on the table
    assert predicted_load(Model, m, x, 0.0, scene) == 0.0
    x[:4, 2] = 0.75 + 0.10  # 16 g of it 10 cm up
    assert predicted_load(Model, m, x, 0.0, scene) == pytest.approx(0.016 * 9.81)
    assert predicted_load(Model, m, x, 1.0, scene) == 0.0  # an open gripper carries nothing
    Model.effects.add({"name": "mass_scale", "params": {"excess": 2.0}})
    assert Model.effects.weight_factor() == pytest.approx(3.0)
    assert predicted_load(Model, m, x, 0.0, scene) == pytest.approx(3 * 0.016 * 9.81)
    Model.effects.add({"name": "stiffness_scale", "params": {"log_scale": -3.0}})  # softer: no heavier
    assert predicted_load(Model, m, x, 0.0, scene) == pytest.approx(3 * 0.016 * 9.81)


def test_bootstrap_with_alternative_baselines_takes_the_smaller_one():
    rng = np.random.default_rng(4)
    low = [1.0 + 0.1 * rng.random(10) for _ in range(3)]
    high = [2.0 * x for x in low]
    cand = {"t": [0.6 * x for x in low]}
    one = bootstrap_explained(low, cand, 200, seed=5)["t"]
    both = bootstrap_explained({"t": [high, low]}, cand, 200, seed=5)["t"]
    np.testing.assert_allclose(both, one)  # the same resamples; the smaller baseline counts
    np.testing.assert_allclose(one, 0.4, atol=1e-9)


def test_discrepancy_detection_compares_episode_residuals_with_the_reference():
    """Rank-based: a measured set whose residuals are 1.5x the reference's is detected, the same
    distribution is not (also with a reference episode where the model failed, like the rope's
    133 mm), and fewer than 3 episodes on a side is not assessed."""
    from soma_ros.discrepancy.workflow import detect_discrepancy

    rng = np.random.default_rng(1)
    ref = np.exp(rng.normal(np.log(0.006), 0.35, 20))
    ref_fail = np.concatenate([ref[:19], [0.133]])
    same = np.exp(rng.normal(np.log(0.006), 0.35, 20))
    worse = 1.5 * np.exp(rng.normal(np.log(0.006), 0.35, 20))
    d = detect_discrepancy(worse, ref_fail, 2000, 0.05)
    assert d["assessed"] and d["detected"] and d["auc"] > 0.7 and d["median_ratio_low"] > 1.0
    for r in (ref, ref_fail):
        d0 = detect_discrepancy(same, r, 2000, 0.05)
        assert d0["assessed"] and not d0["detected"] and 0.3 < d0["auc"] < 0.7
    assert detect_discrepancy(worse, ref[:2], 500, 0.05) == {
        "n_measured": 20, "n_reference": 2, "alpha": 0.05, "measured_median": float(np.median(worse)),
        "reference_median": float(np.median(ref[:2])), "stratified_by_task": False, "tasks": [], "n_unpaired": 0,
        "assessed": False, "detected": None}
    # identical residuals: AUC exactly 0.5 (ties count half), not detected
    assert detect_discrepancy(ref, ref, 500, 0.05)["auc"] == 0.5


def test_discrepancy_detection_pairs_episodes_of_the_same_task():
    """With task labels, measured and reference episodes are compared within a task: an effect
    that doubles the lifts' residual is detected though the drags (a lower own error) mixed with
    the lifts hide it from the pooled statistic. Over 40 draws (12 reference episodes, 20
    measured, half lifts; measured here: 34 of 40 same-task, 0 pooled); with no shift either
    detects at about its 5% level (2 of 40). Labels that do not overlap leave episodes unpaired."""
    from soma_ros.discrepancy.workflow import detect_discrepancy

    lvl = {"lift": 0.008, "drag": 0.003}
    rt, mt = ["lift", "drag"] * 6, ["lift", "drag"] * 10
    hits = {"pooled": 0, "same_task": 0, "pooled_null": 0, "same_task_null": 0}
    for seed in range(40):
        rng = np.random.default_rng(seed)

        def draw(tasks, lift_scale=1.0):
            return [lvl[t] * (lift_scale if t == "lift" else 1.0) * np.exp(rng.normal(0, 0.3)) for t in tasks]

        ref, meas, same = draw(rt), draw(mt, 2.0), draw(mt)
        for key, m in (("", meas), ("_null", same)):
            hits["pooled" + key] += detect_discrepancy(m, ref, 1000, 0.05)["detected"]
            d = detect_discrepancy(m, ref, 1000, 0.05, measured_tasks=mt, reference_tasks=rt)
            assert d["stratified_by_task"] and d["tasks"] == ["drag", "lift"] and d["n_unpaired"] == 0
            hits["same_task" + key] += d["detected"]
    assert hits["same_task"] >= 28 and hits["pooled"] <= 4, hits
    assert hits["same_task_null"] <= 5 and hits["pooled_null"] <= 5, hits
    # only lifts measured: the reference's drags are unpaired; one label missing -> pooled
    d = detect_discrepancy(meas[::2], ref, 500, 0.05, measured_tasks=mt[::2], reference_tasks=rt)
    assert d["tasks"] == ["lift"] and d["n_unpaired"] == 6 and d["n_measured"] == 10
    d = detect_discrepancy(meas, ref, 500, 0.05, measured_tasks=mt[:-1] + [None], reference_tasks=rt)
    assert not d["stratified_by_task"] and d["n_unpaired"] == 0
    d = detect_discrepancy(meas, ref, 500, 0.05, measured_tasks=["fold"] * 20, reference_tasks=rt)
    assert not d["assessed"] and d["n_unpaired"] == 32
    with pytest.raises(ValueError, match="task labels"):
        detect_discrepancy(meas, ref, 500, 0.05, measured_tasks=mt[:3], reference_tasks=rt)


def test_episode_residuals_point_at_episodes_beyond_the_models_own_error():
    """Each measured episode against the largest reference residual of its task, worst first: a
    subset hit hard (2 of 4 lifts at 20x) is flagged, the rest not; a task the reference lacks is
    compared with all reference episodes; no reference: nothing flagged."""
    from soma_ros.discrepancy.workflow import beyond_reference_tail, episode_residuals

    ref = [("lift", 0.008), ("lift", 0.010), ("drag", 0.004), ("drag", 0.005)]
    meas = {"a": {"task": "lift", "residual": 0.20}, "b": {"task": "lift", "residual": 0.009},
            "c": {"task": "lift", "residual": 0.18}, "d": {"task": "drag", "residual": 0.006},
            "e": {"task": "drag", "residual": 0.0045}, "f": {"task": "fold", "residual": 0.009}}
    out, summary = episode_residuals(meas, ref)
    assert list(out) == ["a", "c", "b", "f", "d", "e"]
    chance = summary["expected_by_chance"]
    assert chance == pytest.approx(5 / 3 + 1 / 5)  # 3 lifts and 2 drags vs 2 each, the fold vs all 4
    assert summary["count"] == 3  # groups: lift (3 vs 2), drag (2 vs 2), fold (1 vs all 4)
    assert summary["p_value"] == pytest.approx(beyond_reference_tail([(3, 2), (2, 2), (1, 4)], 3))
    assert out["a"]["vs_reference_median"] == pytest.approx(0.20 / 0.009)
    assert [k for k, v in out.items() if v["beyond_reference"]] == ["a", "c", "d"]
    assert out["a"]["reference_max"] == 0.010 and out["a"]["vs_reference_max"] == pytest.approx(20.0)
    assert out["d"]["reference_max"] == 0.005 and out["f"]["reference_max"] == 0.010 and not out["f"]["beyond_reference"]
    none, summary = episode_residuals(meas, [])
    assert not any(v["beyond_reference"] for v in none.values()) and none["a"]["reference_max"] is None
    assert summary == {"count": 0, "expected_by_chance": 0.0, "p_value": None}
    assert none["a"]["vs_reference_median"] is None


def test_beyond_reference_tail_is_the_exact_law_under_exchangeability():
    """P(at least j measured episodes beyond the largest reference one) against a brute-force
    enumeration of every pooled order (one task) and a simulation of two tasks with continuous
    residuals; it is not the binomial with p = 1 / (m + 1), which ignores the shared maximum."""
    import itertools
    import math

    from soma_ros.discrepancy.workflow import beyond_reference_tail

    k, m = 3, 4
    counts = np.zeros(k + 1)
    for order in set(itertools.permutations("x" * k + "r" * m)):  # the pooled order, largest first
        counts[order.index("r")] += 1
    exact = counts[::-1].cumsum()[::-1] / counts.sum()  # P(X >= j)
    for j in range(k + 1):
        assert beyond_reference_tail([(k, m)], j) == pytest.approx(exact[j])
    assert beyond_reference_tail([(k, m)], 1) == pytest.approx(k / (k + m))
    rng = np.random.default_rng(0)
    groups, draws = [(10, 6), (10, 6)], 40000
    hits = np.zeros(draws, dtype=int)
    for k, m in groups:
        x, y = rng.random((draws, k)), rng.random((draws, m))
        hits += (x > y.max(1, keepdims=True)).sum(1)
    for j in (3, 5, 7):
        assert beyond_reference_tail(groups, j) == pytest.approx((hits >= j).mean(), abs=0.006)
    p7 = beyond_reference_tail(groups, 7)
    binomial = sum(math.comb(20, i) * (1 / 7) ** i * (6 / 7) ** (20 - i) for i in range(7, 21))
    assert p7 == pytest.approx(0.0757, abs=5e-4) and binomial < 0.02  # the shared maximum matters
    assert beyond_reference_tail(groups, 0) == 1.0
    with pytest.raises(ValueError, match="reference"):
        beyond_reference_tail([(3, 0)], 1)


def test_config_rejects_unknown_candidates():
    with pytest.raises(ValueError, match="unknown candidate"):
        load_discrepancy_config("fast", {"candidates": ["no_such_effect"]})


def test_candidates_are_fitted_as_direct_effects_and_recover_a_hidden_wind(monkeypatch):
    """Mechanics of fit_effect with ``direct`` (the config default): the candidate is added as a
    direct effect, and with the world = the same random model + a direct wind the fit recovers it."""
    from soma_ros.core.config import load_model_config
    from soma_ros.core.scenes import synthetic_rope
    from soma_ros.core.simulator import SceneContext, Simulator
    from soma_ros.discrepancy.workflow import EpisodeObs, _rollout, fit_effect, residual_per_frame

    assert load_discrepancy_config("default").direct and load_discrepancy_config("fast").direct
    torch.manual_seed(0)
    sp = synthetic_rope(400, seed=1, center=(0.0, 0.0, 0.0))
    scene = SceneContext.table()
    sim = Simulator(load_model_config("cpu")).eval()
    sim.init_state(sp, scene)  # bind
    world = __import__("copy").deepcopy(sim)
    world.add_effect({"name": "wind", "direct": True, "accel": [0.0, 1.0, 0.0]})
    T = 13
    frames = [4, 8, 12]
    ob = EpisodeObs("e", None, "train", scene.dt, torch.full((T, 4, 3), 3.0), torch.ones(T), sp, frames, [])
    with torch.no_grad():
        ob.points = [st.means[::4].clone() for _, st in _rollout(world, ob, scene, frames)]
    cfg = load_discrepancy_config("fast", {"fit_iters": 40, "fit_lr": 0.1})
    model, losses, values = fit_effect(sim, "wind", [ob], scene, cfg, cfg.fit_iters, log=lambda *a: None)
    assert model.effects.direct_keys == ["wind"] and "wind" not in sim.effects
    # fitted after training: never one of the model's trained terms, so no passive-rule exemption
    assert model.trained_terms() == sim.trained_terms() == ["robot"]
    assert abs(values["accel"][1] - 1.0) < 0.2 and abs(values["accel"][0]) < 0.2, values
    assert float(residual_per_frame(model, ob, scene).mean()) < 0.3 * float(residual_per_frame(sim, ob, scene).mean())
    feat_cfg = load_discrepancy_config("fast", {"direct": False, "fit_iters": 1})
    assert fit_effect(sim, "wind", [ob], scene, feat_cfg, 1, log=lambda *a: None)[0].effects.direct_keys == []
    # a start on a coarse grid (multiples of the term's typical magnitude, here |g|) finds a field Adam's few
    # small steps from 0 do not reach: the world's wind is 9.81 m/s^2 now
    world.effects["wind"].accel.data = torch.tensor([0.0, 9.81, 0.0])
    with torch.no_grad():
        ob.points = [st.means[::4].clone() for _, st in _rollout(world, ob, scene, frames)]
    few = load_discrepancy_config("fast", {"fit_iters": 2, "fit_lr": 0.01})
    plain = fit_effect(sim, "wind", [ob], scene, few, 2, log=lambda *a: None)[2]
    grid = load_discrepancy_config("fast", {"fit_iters": 2, "fit_lr": 0.01, "grid_start": [-2, -1, 1, 2]})
    gridded = fit_effect(sim, "wind", [ob], scene, grid, 2, log=lambda *a: None)[2]
    assert abs(plain["accel"][1]) < 1.0 and abs(gridded["accel"][1] - 9.81) < 0.5, (plain, gridded)
    # the step sizes follow the cosine decay, a step whose gradient is not finite (not taken) counted
    # as one; a fit whose first gradient is such raises no scheduler warning (torch's LambdaLR did)
    import soma_ros.discrepancy.workflow as D

    lrs, checks = [], []
    real_step, real_finite = torch.optim.Adam.step, D._finite_grads

    def step(self, *a, **k):
        lrs.append(self.param_groups[0]["lr"])
        return real_step(self, *a, **k)

    def finite_after_the_first(params):
        checks.append(1)
        return len(checks) > 1 and real_finite(params)

    monkeypatch.setattr(torch.optim.Adam, "step", step)
    monkeypatch.setattr(D, "_finite_grads", finite_after_the_first)
    four = load_discrepancy_config("fast", {"fit_iters": 4, "fit_lr": 0.1})
    with __import__("warnings").catch_warnings(record=True) as caught:
        __import__("warnings").simplefilter("always")
        fit_effect(sim, "wind", [ob], scene, four, 4, log=lambda *a: None)
    assert len(checks) == 4 and len(lrs) == 3
    assert not [w for w in caught if "lr_scheduler" in str(w.message)], [str(w.message) for w in caught]
    f = four.fit_lr_final
    decay = [f + (1 - f) * 0.5 * (1 + math.cos(math.pi * k / 4)) for k in (1, 2, 3)]
    assert [x / lrs[0] for x in lrs] == pytest.approx([d / decay[0] for d in decay])
    with pytest.raises(ValueError, match="grid_episodes"):
        load_discrepancy_config("fast", {"grid_episodes": 0})
    # an unstable model (here a field of NaN) stops with SimulationDiverged at the first bad step: the
    # workflow scores it +inf (the worst value, never a crash of a multi-hour run) and fits through it
    from soma_ros.core.simulator import SimulationDiverged

    bad = __import__("copy").deepcopy(sim)
    bad.add_effect({"name": "wind", "direct": True, "accel": [float("nan"), 0.0, 0.0]})
    with pytest.raises(SimulationDiverged, match="non-finite"):
        list(_rollout(bad, ob, scene, frames))
    assert np.isinf(residual_per_frame(bad, ob, scene)).all()
    _, losses, values = fit_effect(bad, "linear_drag", [ob], scene, grid, 2, log=lambda *a: None)
    assert losses and all(math.isinf(x) for x in losses) and values["coeff"] == [0.0]
    assert decide({}, {}, 0.05, 0.1)[:2] == ("none", [])  # nothing could be ranked


# ----------------------------------------------------------------------------- end to end
@pytest.fixture(scope="module")
def clean_run(tmp_path_factory):
    """A barely trained model on 4 tiny effect-free episodes (the mechanics, not the accuracy)."""
    from conftest import train_tiny_run

    root = tmp_path_factory.mktemp("disc")
    data = root / "clean"
    train_tiny_run(data, root / "run", episodes=4, frames=12)
    return root, data


def test_workflow_end_to_end_negative_control(clean_run):
    from soma_ros.core.checkpoint import load_checkpoint
    from soma_ros.discrepancy.workflow import run_discrepancy

    root, data = clean_run
    cfg = load_discrepancy_config("fast", {"frame_stride": 3, "fit_iters": 2, "eval_frame_stride": 3})
    out = root / "out"
    rep = run_discrepancy(root / "run" / "checkpoint.pt", data, out, cfg, log=lambda *a: None)
    disk = json.loads((out / "report.json").read_text())
    assert disk["named_effect"] == rep["named_effect"]
    # schema
    assert {"named_effect", "ranking", "gap_before", "gap_after"} <= set(disk)
    assert [r["name"] for r in disk["ranking"]] and {r["name"] for r in disk["ranking"]} == set(cfg.candidates)
    for r in disk["ranking"]:
        assert math.isfinite(r["explained_fraction"]) and r["uncertainty"] >= 0 and r["explained_fraction"] <= 1
    # the own-error control ran on the model's training data (here the measured data itself):
    # every candidate was calibrated there first
    held_in_training = [r["name"] for r in json.loads((data / "manifest.json").read_text())["episodes"]
                        if r["split"] != "train"]
    assert disk["decision"]["calibrated_on_reference"] and disk["episodes"]["reference"] == held_in_training
    # too few reference episodes to tell a discrepancy from the model's own error: said, not guessed
    det = disk["discrepancy"]
    assert det["n_reference"] == len(held_in_training) < 3 and det["assessed"] is False and det["detected"] is None
    assert "not assessed" in (out / "report.md").read_text()
    per = disk["episode_residuals"]  # every measured episode, worst first, against the reference's largest
    assert sorted(per) == sorted(disk["episodes"]["fit"] + disk["episodes"]["heldout"])
    assert [v["residual"] for v in per.values()] == sorted((v["residual"] for v in per.values()), reverse=True)
    assert all(v["reference_max"] > 0 and isinstance(v["beyond_reference"], bool) for v in per.values())
    assert "Episodes, worst first" in (out / "report.md").read_text()
    assert disk["episodes_beyond_reference"]["count"] == sum(v["beyond_reference"] for v in per.values())
    assert 0.0 < disk["episodes_beyond_reference"]["p_value"] <= 1.0
    assert "P(at least" in (out / "report.md").read_text()
    assert all("reference_parameters" in f for f in disk["fits"].values())
    sc = [r["score"] for r in disk["ranking"]]
    assert sc == sorted(sc, reverse=True)
    # the reference world records efforts: the wrist load ranks the candidates too
    assert disk["decision"]["wrist_load"]
    for r in disk["ranking"]:
        assert -1.0 <= max(r["load_explained"], -1.0) <= 1.0 and r["load_ci_low"] <= r["load_ci_high"]
        assert r["score"] == pytest.approx(r["explained_fraction"] + max(r["load_explained"], -1.0))
    assert "wrist load" in (out / "report.md").read_text()
    for k in ("gap_before", "gap_after"):
        assert disk[k]["rmse"] > 0 and disk[k]["chamfer"] > 0 and disk[k]["points"] > 0
    # negative control: effect-free data -> nothing significant, and then the model is unchanged
    assert disk["named_effect"] == "none", disk["decision"]
    assert disk["gap_after"]["rmse"] == pytest.approx(disk["gap_before"]["rmse"])
    for f in ("report.md", "ranking.png", "residual_time.png", "residual_clusters.png", "gap.png"):
        assert (out / f).is_file(), f
    sim = load_checkpoint(out / "model" / "checkpoint.pt")
    assert set(sim.effects.keys()) == {"gravity", "support", "robot"}
    # a candidate added to the trained model changes nothing until fitted (zero-init), bit for bit
    from soma_ros.discrepancy.workflow import EpisodeObs, residual_per_frame
    from soma_ros.evaluation.evaluate import EvalContext
    from soma_ros.training.config import load_train_config

    ctx = EvalContext(data, load_train_config(root / "run" / "train_config.yaml"), root / "run" / "scene")
    ref = ctx.refs[0]
    ep = ctx.store.episode(ref.name)
    ob = EpisodeObs(ref.name, ref.task, ref.split, ep.dt, ep.control_points.float(), ep.gripper.float(),
                    ctx.store.initial_splats(ref.name), [3, 6, 9],
                    [ep.object_points([t])[0][:64] for t in (3, 6, 9)])
    r0 = residual_per_frame(sim, ob, ctx.scene)
    for name in ("table_friction", "gripper_slip", "mass_scale"):
        sim.add_effect({"name": name})
    np.testing.assert_array_equal(residual_per_frame(sim, ob, ctx.scene), r0)


def test_calibration_on_the_models_own_conditions_separates_its_error_from_the_new_effect():
    """The own-error control of rank_candidates on a synthetic world: the model misses a wind
    a0 on ANY data (its own error), the new data has a0 + a1. Calibrated on the reference
    (a0 only), the wind candidate is named on the new data for a1 alone, and on data like the
    reference it explains nothing; without the calibration, a0 alone is "named" (the error the
    control exists for). The observed points carry 3 mm of noise, as back-projected depth does:
    without it the calibrated model matches the world exactly, and relative gains on a residual
    near zero are fit noise (fractions of 0.24 from parameters equal to 0.02 m/s^2)."""
    from benchmarks.discrepancy_jobs import wind_episodes
    from soma_ros.core.config import load_model_config
    from soma_ros.core.scenes import synthetic_rope
    from soma_ros.core.simulator import SceneContext, Simulator
    from soma_ros.discrepancy.workflow import rank_candidates, residual_per_frame

    torch.manual_seed(0)
    scene = SceneContext.table()
    sim = Simulator(load_model_config("cpu")).eval()
    T = 13

    def episodes(accel, seeds, split):
        return wind_episodes(sim, scene, accel, seeds, split, T)

    sim.init_state(synthetic_rope(300, seed=1, center=(0.0, 0.0, 0.3)), scene)  # bind
    a0, a01 = [0.0, 0.6, 0.0], [0.6, 0.6, 0.0]
    ref = episodes(a0, [1, 2], "train")
    cfg = load_discrepancy_config("fast", {"candidates": ["wind", "linear_drag"], "fit_iters": 24,
                                           "line_search": [0.5, 1.0, 1.5], "bootstrap": 300})
    quiet = lambda *a: None  # noqa: E731
    for accel, want in ((a01, "wind"), (a0, "none")):
        fit, held = episodes(accel, [3, 4], "train"), episodes(accel, [5, 6], "test")
        base = [residual_per_frame(sim, o, scene) for o in held]
        named, ranking, decision, fits, _, _ = rank_candidates(sim, fit, held, base, scene, cfg, quiet, ref)
        assert named == want, (accel, decision, ranking)
        assert decision["calibrated_on_reference"]
        assert fits["wind"]["reference_parameters"]["accel"][1] > 0.3  # the calibration took up a0
        if want == "wind":
            assert fits["wind"]["parameters"]["accel"][0] > 0.3  # ... and the re-fit the new a1
    # without the calibration the model's own error (a0) is "named" on data without a new effect
    fit, held = episodes(a0, [3, 4], "train"), episodes(a0, [5, 6], "test")
    base = [residual_per_frame(sim, o, scene) for o in held]
    one = rank_candidates(sim, fit, held, base, scene, cfg, quiet)
    assert one[0] == "wind"
    # the candidates fitted in 2 worker processes: the same fits and ranking, and the returned models
    # (rebuilt from the fitted values) give the held-out residuals the fits were scored with
    two = rank_candidates(sim, fit, held, base, scene, dataclasses.replace(cfg, jobs=2), quiet)
    assert two[0] == one[0] and two[1] == one[1]
    for name, rec in one[3].items():
        assert two[3][name]["parameters"] == rec["parameters"]
        assert two[3][name]["explained_fraction"] == rec["explained_fraction"]
        again = sum(float(residual_per_frame(two[4][name], o, scene).sum()) for o in held)
        assert 1.0 - again / sum(float(b.sum()) for b in base) == pytest.approx(rec["explained_vs_unchanged"], abs=1e-9)
    with pytest.raises(ValueError, match="jobs"):
        load_discrepancy_config("fast", {"jobs": 0})


def test_cli_reports_a_bad_reference_dataset_clearly(clean_run, tmp_path, capsys):
    from soma_ros.cli import main

    root, data = clean_run
    rc = main(["discrepancy", "--checkpoint", str(root / "run"), "--data", str(data), "--out", str(tmp_path / "o"),
               "--config", "fast", "--reference", str(tmp_path / "no_such_dataset")])
    assert rc == 2
    err = capsys.readouterr().err
    assert "reference_data" in err and "no_such_dataset" in err and "manifest.json" in err


def test_stratified_holdout_holds_out_every_task():
    from soma_ros.data.dataset import EpisodeRef
    from soma_ros.discrepancy.workflow import heldout_names

    tasks = ["lift", "drag", "fold"] * 3 + ["lift"]  # the cloth dataset's cycle, 10 episodes
    refs = [EpisodeRef(f"e{i}", None, "test" if i in (3, 6, 9) else "train", t) for i, t in enumerate(tasks)]
    cfg = load_discrepancy_config("default")
    held = heldout_names(refs, cfg)
    assert sorted({t for r, t in zip(refs, tasks) if r.name in held}) == ["drag", "fold", "lift"]
    assert held == ["e4", "e5", "e6"]  # round(0.3 x (4, 3, 3)) = 1 each, mid-group, in manifest order
    # a manifest split by name is still possible (here: the random split held out lifts only)
    assert heldout_names(refs, load_discrepancy_config("default", {"heldout_split": "test"})) == ["e3", "e6", "e9"]


def test_load_model_exempts_the_trained_terms_by_default(clean_run):
    from soma_ros.discrepancy.workflow import load_model

    root, _ = clean_run
    ck = root / "run" / "checkpoint.pt"
    sim = load_model(ck, load_discrepancy_config("default", {"passive_exempt_trained": False}))
    assert sim.config.dynamics.passive_friction == 0.5 and sim.config.dynamics.passive_exempt == []
    sim = load_model(ck, load_discrepancy_config("default"))
    assert sim.config.dynamics.passive_exempt == ["robot"]  # not gravity / support (reference terms)
    assert sim.config.dynamics.passive_exempt_closed is True  # as the live node: only with the gripper closed
    assert sim.trained_terms() == ["robot"]
    sim.add_effect({"name": "wind", "direct": True})
    assert sim.config.dynamics.passive_exempt == ["robot"]  # a candidate added later stays bounded
    # a model the workflow writes (its named term fitted after training) keeps that across a
    # checkpoint, so the live node (LiveSimulator: trained_terms) does not exempt the named term
    from soma_ros.core.checkpoint import load_checkpoint, save_checkpoint

    sim.add_effect({"name": "gripper_slip", "direct": True, "fitted_after_training": True})
    assert sim.trained_terms() == ["robot", "wind"]
    save_checkpoint(root / "posthoc.pt", sim)
    back = load_checkpoint(root / "posthoc.pt")
    assert back.trained_terms() == ["robot", "wind"] and "gripper_slip" in back.effects
    assert [s.to_yaml_dict().get("fitted_after_training") for s in back.effects.specs] == [None, None, None, None, True]


def _falling_rope(excess: float):
    """(model, observation, scene): a synthetic rope falling freely for 5 steps, observed (frames 2
    and 4) in a world whose direct mass_scale term has ``excess``; the model has no such term."""
    from soma_ros.core.config import load_model_config
    from soma_ros.core.scenes import synthetic_rope
    from soma_ros.core.simulator import SceneContext, Simulator
    from soma_ros.discrepancy.workflow import EpisodeObs, _rollout

    torch.manual_seed(0)
    sp = synthetic_rope(300, seed=1, center=(0.0, 0.0, 0.3))
    scene = SceneContext.table()
    sim = Simulator(load_model_config("cpu")).eval()
    sim.init_state(sp, scene)
    world = __import__("copy").deepcopy(sim)
    world.add_effect({"name": "mass_scale", "direct": True, "excess": excess})
    T, frames = 5, [2, 4]  # before the falling rope reaches the table
    ob = EpisodeObs("e", None, "train", scene.dt, torch.full((T, 4, 3), 3.0), torch.ones(T), sp, frames, [])
    with torch.no_grad():
        ob.points = [st.means[::4].clone() for _, st in _rollout(world, ob, scene, frames)]
    return sim, world, ob, scene


def test_fits_stay_inside_the_terms_physical_range():
    """A world whose lifted rope is pulled down by 20 g: the mass_scale fit would take an excess of
    about 20 (21 times the mass), outside its declared range [-0.9, 9]; the fit (grid start, Adam,
    line search) stops on the bound and says so. Unbounded terms are unchanged by the projection."""
    from soma_ros.core.effects import EFFECTS, build_effect
    from soma_ros.discrepancy.workflow import _line_search, _rollout, fit_effect

    for name, cls in EFFECTS.items():  # every declared bound names a parameter and is an interval
        eff = build_effect(name)
        for n, (lo, hi) in cls.bounds.items():
            assert isinstance(getattr(eff, n), torch.nn.Parameter) and lo < 0.0 < hi, (name, n)
    sim, world, ob, scene = _falling_rope(20.0)  # the residual falls all the way to 20
    frames = ob.frames
    cfg = load_discrepancy_config("fast", {"fit_iters": 6, "fit_lr": 0.5, "grid_start": [5, 10, 20, 40]})
    model, _, values = fit_effect(sim, "mass_scale", [ob], scene, cfg, cfg.fit_iters, log=lambda *a: None)
    assert values["excess"] == [pytest.approx(9.0)], values
    assert model.effects["mass_scale"].project_() == ["excess"]  # on its bound, reported as such
    zero = [torch.zeros_like(p) for _, p in model.acting_parameters("mass_scale")]
    a, _ = _line_search(model, "mass_scale", zero, [ob], scene, [1.5], float("inf"))
    assert a == 1.5 and float(model.effects["mass_scale"].excess) == pytest.approx(9.0)  # overshoot clamped
    # within its range the fit is free: the same world at excess 3 is recovered near 3
    world.effects["mass_scale"].excess.data.fill_(3.0)
    with torch.no_grad():
        ob.points = [st.means[::4].clone() for _, st in _rollout(world, ob, scene, frames)]
    values = fit_effect(sim, "mass_scale", [ob], scene, load_discrepancy_config(
        "fast", {"fit_iters": 6, "fit_lr": 0.1, "grid_start": [1, 2, 3, 4]}), 6, log=lambda *a: None)[2]
    assert 2.0 < values["excess"][0] < 4.0, values
    wind = build_effect({"name": "wind", "accel": [0.0, 0.0, -400.0]})
    assert wind.project_() == [] and wind.accel.tolist() == [0.0, 0.0, -400.0]


def test_the_fit_weighs_the_wrist_load_as_the_ranking_does():
    """A falling rope held by a closed gripper whose points say mass x4 (excess 3) while the wrist feels
    x2 (excess 1): fitted on the 3D residual alone the mass term goes near excess 3; with the wrist load
    in the fit (``load_in_fit``, each channel relative to the start, excess 0) it stays near 1, where the
    load's relative error falls three times as fast per unit as the points' (both are linear in the
    excess here), and its result has the lower value of the two-channel objective. Without efforts the
    load has no weight."""
    import copy

    from soma_ros.discrepancy.workflow import FitObjective, _rollout, fit_effect, objective_at_start, load_tensor, predicted_load

    sim, world, ob, scene = _falling_rope(3.0)
    ob.gripper = torch.zeros_like(ob.gripper)  # closed: the rope's weight is on the wrist
    wrist = copy.deepcopy(sim)
    wrist.add_effect({"name": "mass_scale", "direct": True, "excess": 1.0})
    with torch.no_grad():
        ob.load = np.array([predicted_load(wrist, ob.init.mass, st.means, 0.0, scene)
                            for _, st in _rollout(wrist, ob, scene, ob.frames)])
    # the load is differentiable in the mass term: d load / d excess = the lifted weight
    probe = copy.deepcopy(wrist)
    excess = probe.effects["mass_scale"].excess
    excess.requires_grad_(True)
    load = load_tensor(probe, ob.init.mass, ob.init.means, 0.0, scene)
    load.backward()
    assert float(excess.grad) == pytest.approx(float(load.detach()) / 2.0, rel=1e-5)
    off = load_discrepancy_config("fast", {"fit_iters": 6, "fit_lr": 0.1, "grid_start": [1, 2, 3, 4],
                                           "load_in_fit": False})
    on = dataclasses.replace(off, load_in_fit=True)
    assert objective_at_start(sim, [ob], scene, off)[0] == FitObjective()
    both, start = objective_at_start(sim, [ob], scene, on)
    assert both.load_weight > 0 and start == pytest.approx(2 * float(objective_at_start(sim, [ob], scene, off)[1]))
    no_efforts = dataclasses.replace(ob, load=None)
    assert objective_at_start(sim, [no_efforts], scene, on)[0] == FitObjective()
    fitted = {}
    for key, objective in (("3d", FitObjective()), ("both", both)):
        model, _, values = fit_effect(sim, "mass_scale", [ob], scene, off, 6, log=lambda *a: None, objective=objective)
        fitted[key] = (values["excess"][0], both.total(model, [ob], scene))
    assert 2.5 < fitted["3d"][0] < 3.5, fitted
    assert 0.5 < fitted["both"][0] < 1.5, fitted
    assert fitted["both"][1] < fitted["3d"][1], fitted


def test_the_line_search_continues_past_its_smallest_scale_only_when_asked():
    """``line_search_extend``: a best scale at the end of the list is followed beyond it (that end's
    ratio) while the residual falls, and stops at the first scale that does not lower it."""
    from soma_ros.discrepancy.workflow import _line_search

    with pytest.raises(ValueError, match="line_search_extend"):
        load_discrepancy_config("fast", {"line_search_extend": -1})
    sim, _, ob, scene = _falling_rope(1.0)  # the residual is smallest at the world's excess
    found = []
    for extend in (0, 3):
        model = __import__("copy").deepcopy(sim)
        model.add_effect({"name": "mass_scale", "direct": True, "excess": 8.0})  # the "fit" overshot 8x
        zero = [torch.zeros_like(p) for _, p in model.acting_parameters("mass_scale")]
        a, _ = _line_search(model, "mass_scale", zero, [ob], scene, [0.5, 1.0], float("inf"), extend)
        found.append((a, float(model.effects["mass_scale"].excess.detach())))
    assert found[0] == (0.5, pytest.approx(4.0))  # the list only
    assert found[1] == (0.125, pytest.approx(1.0))  # 0.25, 0.125 lower it; 0.0625 does not: stop


def _grid_search_on(monkeypatch, residual_of, overrides: dict) -> dict:
    """{key: (hold, sag)} where ``_grid_start`` leaves gripper_slip's two direct parameters, from
    (0, 0), for each config override set in ``overrides`` ({key: {option: value}}), with the
    residual a function ``residual_of(hold, sag)`` of the term's parameters (the search itself is
    what is tested; the rollouts it stands for are tested with the workflow)."""
    import soma_ros.discrepancy.workflow as D
    from soma_ros.core.config import load_model_config
    from soma_ros.core.simulator import Simulator

    sim = Simulator(load_model_config("cpu")).eval()
    sim.add_effect({"name": "gripper_slip", "direct": True})
    eff = sim.effects["gripper_slip"]
    assert [n for n, _ in sim.acting_parameters("gripper_slip")] == ["hold", "sag"]
    monkeypatch.setattr(D, "residual_per_frame", lambda model, obs, scene: torch.tensor(
        [residual_of(float(eff.hold.detach()), float(eff.sag.detach()))]))
    found = {}
    for key, extra in overrides.items():
        with torch.no_grad():
            eff.hold.zero_()
            eff.sag.zero_()
        cfg = load_discrepancy_config("fast", {"grid_start": [-2, -1, 1, 2, 3], **extra})
        D._grid_start(sim, "gripper_slip", [object()], None, cfg, log=lambda *a: None)
        found[key] = (float(eff.hold.detach()), float(eff.sag.detach()))
    return found


def test_grid_start_searches_two_acting_elements_jointly_where_one_at_a_time_stops_early(monkeypatch):
    """A residual whose best is reachable only by changing both elements at once from a first step
    that looks good alone: hold = 1 alone halves it, sag = 2 with hold = 0 takes it to a tenth, and
    with hold = 1 every sag is worse than 0.5. One element at a time (grid_joint 1) stops at
    (1, 0); the joint grid (grid_joint 2, the default) finds (0, 2)."""
    table = {(0.0, 0.0): 1.0, (1.0, 0.0): 0.5, (0.0, 2.0): 0.1}
    found = _grid_search_on(monkeypatch, lambda h, s: table.get((h, s), 2.0 if h != 0.0 else 1.5),
                            {1: {"grid_joint": 1}, 2: {"grid_joint": 2}})
    assert found == {1: (1.0, 0.0), 2: (0.0, 2.0)}
    with pytest.raises(ValueError, match="grid_joint"):
        load_discrepancy_config("fast", {"grid_joint": 0})


def test_grid_refine_finds_a_threshold_below_the_grids_first_step(monkeypatch):
    """A threshold response: hold = 0 is off (residual 1), any hold > 0 is on and best at 0.125, a
    quarter-decade (in log2) per doubling away from it, and hold < 0 is worse than off. The coarse
    grid (multiples 1, 2, 3 of the scale 1) stops at its first step, hold = 1; grid_refine 4 then
    tries 1/2 ... 1/16 of that move and finds 0.125, where Adam would get no gradient to follow.
    sag, never moved by the grid, is left at its start."""
    import math

    def residual(h, s):
        return (1.0 if h == 0.0 else (2.0 if h < 0 else 0.1 + 0.05 * abs(math.log2(h / 0.125)))) + abs(s)

    found = _grid_search_on(monkeypatch, residual, {0: {"grid_refine": 0}, 4: {"grid_refine": 4}})
    assert found == {0: (1.0, 0.0), 4: (0.125, 0.0)}, found

    def residual_quarter(h, s):  # the same threshold, best at 1/4 of the grid's step, after a better 1/2
        return (1.0 if h == 0.0 else (2.0 if h < 0 else 0.1 + 0.05 * abs(math.log2(h / 0.25)))) + abs(s)

    # every fraction is of the grid's own move: 1/4 is tried even though 1/2 improved first
    assert _grid_search_on(monkeypatch, residual_quarter, {4: {"grid_refine": 4}}) == {4: (0.25, 0.0)}
    with pytest.raises(ValueError, match="grid_refine"):
        load_discrepancy_config("fast", {"grid_refine": -1})
