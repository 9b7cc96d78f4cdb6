"""Training that starts from the priors: the zero-initialised network, the network switch (the
``prior_only`` baseline), the optimiser's parameter groups and warm-up, validation stratified over
the tasks and the selection score (soma_ros/training/train.py, soma_ros/training/config.py, soma_ros/evaluation/baselines.py,
soma_ros/evaluation/accuracy.py).

Fast: no dataset, no training run (test/training/test_trainer.py trains for real and checks the files a run
writes, ``val_tasks.csv`` / ``val_tasks.png`` included).
"""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch

from soma_ros.core.scenes import synthetic_rope
from soma_ros.core.simulator import RobotAction, SceneContext, Simulator

torch.set_num_threads(1)


def _tiny_sim(out_init_scale=None, seed=0) -> Simulator:
    from soma_ros.training.config import load_train_config

    over = {} if out_init_scale is None else {"model_overrides": {"gnn": {"out_init_scale": out_init_scale}}}
    torch.manual_seed(seed)
    return Simulator(load_train_config("tiny", over).model_config()).eval()


def _grasp_rollout(sim: Simulator, steps: int = 25):
    """A gripper closing on one end of a rope lying on the table, then lifting and dragging it."""
    sp = synthetic_rope(600, seed=0, center=(0.0, 0.0, 0.0))
    end = sp.means[sp.means[:, 0] > 0.12].mean(0)
    g = torch.Generator().manual_seed(0)
    cp0 = end + 0.01 * torch.randn(20, 3, generator=g)
    actions = [RobotAction(cp0 + torch.tensor([0.002 * i, 0.001 * i, 0.003 * i]), 0.0 if i > 3 else 1.0)
               for i in range(steps)]
    with torch.no_grad():
        s0 = sim.init_state(sp, SceneContext.table())
        states = sim.rollout(s0, actions)
    return s0, states


def test_the_untrained_tiny_model_is_its_priors_bit_for_bit():
    """``gnn.out_init_scale: 0`` (config/train/tiny.yaml): the decoder's last layer is zero, so the
    network's output is exactly zero and a rollout is bit for bit the one with the network switched
    off (:meth:`Simulator.set_network`) -- the priors alone. Tolerance 0."""
    sim = _tiny_sim()
    assert sim.config.gnn.out_init_scale == 0.0
    assert float(sim.gnn.decoder.last.weight.detach().abs().max()) == 0.0
    s0, on = _grasp_rollout(sim)
    moved = float((on[-1].means - s0.means).norm(dim=-1).max())
    assert moved > 0.01, moved  # the priors (robot coupling and carry) move the rope: the check is not vacuous
    sim.set_network(False)
    _, off = _grasp_rollout(sim)
    for a, b in zip(on, off):
        assert torch.equal(a.means, b.means) and torch.equal(a.covs, b.covs) and torch.equal(a.quats, b.quats)
    # the same switch on a network whose output is not zero changes the rollout
    sim_r = _tiny_sim(out_init_scale=1.0)
    _, on_r = _grasp_rollout(sim_r)
    _, off_r = _grasp_rollout(sim_r.set_network(False))
    assert not torch.equal(on_r[-1].means, off_r[-1].means)
    assert torch.equal(off_r[-1].means, off[-1].means)  # network off: the weights do not matter
    assert "network_enabled" not in sim.state_dict()


def test_zero_init_network_still_learns():
    """Zero last layer: the first gradient reaches that layer (and the physical terms); once it has
    moved, the gradient reaches the earlier layers too."""
    from soma_ros.training.train import param_groups

    sim = _tiny_sim().train()
    sp = synthetic_rope(400, seed=1, center=(0.0, 0.0, 0.0))
    end = sp.means[sp.means[:, 0] > 0.12].mean(0)
    cp = end + 0.01 * torch.randn(16, 3, generator=torch.Generator().manual_seed(1))

    def loss_grads():
        sim.zero_grad(set_to_none=True)
        s = sim.init_state(sp, SceneContext.table())
        for i in range(6):
            s = sim.step(s, RobotAction(cp + torch.tensor([0.0, 0.0, 0.004 * i]), 0.0))
        (s.means[:, 2].mean() + s.means[:, 0].std()).backward()
        return {n: (p.grad is not None and float(p.grad.abs().max()) > 0) for n, p in sim.named_parameters()}

    g = loss_grads()
    last = next(n for n, p in sim.named_parameters() if p is sim.gnn.decoder.last.weight)
    assert g[last]  # the zero layer itself
    assert not g["gnn.node_encoder.net.0.weight"]  # behind the zero layer
    assert any(v for n, v in g.items() if n.startswith("effects."))
    with torch.no_grad():
        sim.gnn.decoder.last.weight.normal_(0.0, 1e-3)
    g = loss_grads()
    assert g["gnn.node_encoder.net.0.weight"]
    groups = param_groups(sim)
    names = {id(p): n for n, p in sim.named_parameters()}
    assert all(names[id(p)].startswith("gnn.") or names[id(p)] == "splat_attrs" for p in groups["network"])
    assert groups["physics"] and all(names[id(p)].startswith("effects.") for p in groups["physics"])
    assert sum(len(v) for v in groups.values()) == len(list(sim.parameters()))


def test_network_contribution_is_zero_for_the_priors_and_its_penalty_pulls_it_back():
    """``SimState.network_sq`` (``loss.network_weight``'s term): exactly 0 on every step of the
    zero-initialised network, None with the network off, > 0 for a network whose output is not zero;
    its gradient reaches the decoder's last layer, and a step down it shrinks the contribution."""
    from soma_ros.training.config import ConfigError, load_train_config
    from soma_ros.training.train import total_loss

    _, states = _grasp_rollout(_tiny_sim())
    assert all(s.network_sq is not None and float(s.network_sq) == 0.0 for s in states)
    _, off = _grasp_rollout(_tiny_sim().set_network(False))
    assert all(s.network_sq is None for s in off)

    sim = _tiny_sim(out_init_scale=1.0).train()
    sp = synthetic_rope(400, seed=1, center=(0.0, 0.0, 0.0))
    end = sp.means[sp.means[:, 0] > 0.12].mean(0)
    cp = end + 0.01 * torch.randn(16, 3, generator=torch.Generator().manual_seed(1))

    def contribution():
        s = sim.init_state(sp, SceneContext.table())
        total = s.means.new_zeros(())
        for i in range(6):
            s = sim.step(s, RobotAction(cp + torch.tensor([0.0, 0.0, 0.004 * i]), 0.0))
            total = total + s.network_sq
        return total / 6

    c0 = contribution()
    assert float(c0.detach()) > 0
    cfg = load_train_config("tiny", {"loss": {"network_weight": 10.0}})
    z = c0.new_zeros(())
    terms = {"img": z, "depth": z, "points": z, "momentum": z, "network": c0}
    loss = total_loss(terms, cfg)
    assert float(loss.detach()) == pytest.approx(10.0 * float(c0.detach()))
    assert float(total_loss({k: v for k, v in terms.items() if k != "network"}, cfg)) == 0.0  # validation: no term
    sim.zero_grad(set_to_none=True)
    loss.backward()
    last = sim.gnn.decoder.last.weight
    assert last.grad is not None and float(last.grad.abs().max()) > 0
    with torch.no_grad():
        for prm in sim.gnn.parameters():
            if prm.grad is not None:
                prm -= 1e-3 * prm.grad / prm.grad.norm().clamp_min(1e-30)
    assert float(contribution().detach()) < float(c0.detach())
    with pytest.raises(ConfigError, match="network_weight"):
        load_train_config("tiny", {"loss": {"network_weight": -1.0}})


def test_parameter_groups_learning_rates_and_warmup():
    from soma_ros.training.config import ConfigError, load_train_config
    from soma_ros.training.train import lr_at, make_optimizer

    cfg = load_train_config("tiny", {"optim": {"lr": 2e-3, "lr_final_factor": 0.5,
                                               "network": {"lr": 1e-3, "warmup_iters": 10},
                                               "physics": {"lr": None, "warmup_iters": 0}}})
    total = cfg.schedule.total_iters
    assert cfg.optim.group_lr("physics") == 2e-3 and cfg.optim.group_lr("network") == 1e-3
    assert lr_at(cfg, 0, "physics") == pytest.approx(2e-3)
    assert lr_at(cfg, 0, "network") == pytest.approx(1e-3 / 10)
    assert lr_at(cfg, 4, "network") == pytest.approx(lr_at(cfg, 4, None) / 2e-3 * 1e-3 * 5 / 10)
    assert lr_at(cfg, 9, "network") == pytest.approx(lr_at(cfg, 9, None) / 2)  # warm-up done
    assert lr_at(cfg, total, "network") == pytest.approx(1e-3 * 0.5)  # cosine to lr * lr_final_factor
    assert lr_at(cfg, total, "physics") == pytest.approx(2e-3 * 0.5)
    sim = _tiny_sim()
    sim.bind(synthetic_rope(300, seed=0, center=(0.0, 0.0, 0.0)))
    opt = make_optimizer(sim, cfg)
    assert [g["name"] for g in opt.param_groups] == ["network", "physics"]
    assert opt.param_groups[0]["lr"] == pytest.approx(1e-4) and opt.param_groups[1]["lr"] == pytest.approx(2e-3)
    assert any(p is sim.splat_attrs for p in opt.param_groups[0]["params"])
    for bad, match in (({"network": {"lr": -1.0}}, "optim.network.lr"),
                       ({"physics": {"warmup_iters": 1.5}}, "optim.physics.warmup_iters"),
                       ({"network": {"rate": 1.0}}, "optim.network.rate: unknown key")):
        with pytest.raises(ConfigError, match=match):
            load_train_config("tiny", {"optim": bad})
    with pytest.raises(ConfigError, match="run.score_terms"):
        load_train_config("tiny", {"run": {"score_terms": ["img", "colour"]}})
    with pytest.raises(ConfigError, match="run.score_terms"):
        load_train_config("tiny", {"run": {"score_terms": []}})


def _refs(spec):
    from soma_ros.data.dataset import EpisodeRef

    return [EpisodeRef(name, Path("/nonexistent") / name, "train", task) for name, task in spec]


def test_validation_is_stratified_over_the_training_tasks():
    from soma_ros.data.config import DataConfig
    from soma_ros.training.train import split_validation

    refs = _refs([("e0", "lift"), ("e1", "drag"), ("e2", "lift"), ("e3", "fold"), ("e4", "lift"), ("e5", "drag"),
                  ("e6", "lift")])
    train, val = split_validation(refs, None, DataConfig(val_split=None, val_holdout=1))
    # the last episode of every task with more than one; fold's only episode stays in training
    assert [r.name for r in val] == ["e5", "e6"]
    assert [r.name for r in train] == ["e0", "e1", "e2", "e3", "e4"]
    train, val = split_validation(refs, None, DataConfig(val_split=None, val_holdout=2))
    assert [r.name for r in val] == ["e4", "e5", "e6"]  # round-robin; drag keeps one of its two for training
    assert {r.task for r in train} == {"lift", "drag", "fold"}
    train, val = split_validation(refs, None, DataConfig(val_split=None, val_holdout=2, val_stratify=False))
    assert [r.name for r in val] == ["e5", "e6"]  # the last two, whatever their task
    # a validation split of its own: only reordered round-robin
    vsplit = _refs([("v0", "lift"), ("v1", "lift"), ("v2", "drag")])
    train, val = split_validation(refs, vsplit, DataConfig(val_split="val"))
    assert [r.name for r in val] == ["v0", "v2", "v1"] and len(train) == len(refs)
    # no task recorded: one group, the last episodes
    train, val = split_validation(_refs([("a", None), ("b", None), ("c", None)]), None,
                                  DataConfig(val_split=None, val_holdout=1))
    assert [r.name for r in val] == ["c"] and [r.name for r in train] == ["a", "b"]


def test_selection_score_weighs_every_task_and_geometry():
    from soma_ros.training.train import selection_score

    ref = {"lift": {"img": 0.06, "depth": 0.06, "points": 0.006, "val_loss": 0.12},
           "drag": {"img": 0.03, "depth": 0.02, "points": 0.003, "val_loss": 0.05}}
    terms = ["img", "depth", "points"]
    assert selection_score(ref, ref, terms) == 1.0
    # lift's image loss halves while drag's point distance doubles: the drag's geometric loss counts
    worse = {"lift": dict(ref["lift"], img=0.03), "drag": dict(ref["drag"], points=0.006)}
    assert selection_score(worse, ref, terms) == pytest.approx((0.5 + 1 + 1 + 1 + 1 + 2) / 6)
    assert selection_score(worse, ref, ["img"]) < 1.0 < selection_score(worse, ref, ["points"])
    assert selection_score({"lift": ref["lift"]}, ref, terms) == math.inf  # a task not validated
    assert selection_score({**ref, "lift": dict(ref["lift"], depth=float("nan"))}, ref, terms) == math.inf


def test_prior_only_baseline_loads_a_checkpoint_with_the_network_off(tmp_path, monkeypatch):
    from soma_ros.core.checkpoint import save_checkpoint
    from soma_ros.evaluation.baselines import VARIANTS, load_model

    sim = _tiny_sim(out_init_scale=1.0)
    sim.bind(synthetic_rope(300, seed=0, center=(0.0, 0.0, 0.0)))
    save_checkpoint(tmp_path / "checkpoint.pt", sim, extra={"iteration": 5})
    loads = []
    real_load = torch.load
    monkeypatch.setattr(torch, "load", lambda *a, **k: loads.append(a[0]) or real_load(*a, **k))
    full, prior = load_model(tmp_path / "checkpoint.pt"), load_model(tmp_path, network=False)
    assert len(loads) == 2, loads  # each model reads its file once
    assert full.describe()["network"] is True and prior.describe()["network"] is False
    assert prior.sim.network_enabled is False and full.sim.network_enabled is True
    assert "prior_only" in VARIANTS and {"full", "static", "state_only", "spring_mass", "img_only",
                                         "no_mrt"} <= set(VARIANTS)


def test_prior_comparison_per_task_and_on_the_mean():
    from soma_ros.evaluation.accuracy import prior_comparison, prior_markdown, task_means

    eps = {"a": {"task": "lift", "rmse": 0.010, "chamfer": 0.004}, "b": {"task": "lift", "rmse": 0.014, "chamfer": 0.006},
           "c": {"task": "drag", "rmse": 0.020, "chamfer": float("nan")}}
    tm = task_means(eps)
    assert tm["lift"]["rmse"] == pytest.approx(0.012) and tm["lift"]["episodes"] == 2
    assert math.isnan(tm["drag"]["chamfer"])
    full = {"lift": {"rmse": 0.010, "chamfer": 0.004}, "drag": {"rmse": 0.0205, "chamfer": 0.009}}
    prior = {"lift": {"rmse": 0.012, "chamfer": 0.005}, "drag": {"rmse": 0.020, "chamfer": 0.008}}
    pc = prior_comparison({"full": {"test": full}, "prior_only": {"test": prior}})
    assert pc["full_better_on_mean"] == {"rmse": True, "chamfer": True}
    assert pc["worst_task_relative"]["rmse"] == pytest.approx(0.025)
    assert pc["worst_task_relative"]["chamfer"] == pytest.approx(0.125) and not pc["within_tolerance"]
    text = "\n".join(prior_markdown(pc))
    assert "| drag |" in text and "NOT met" in text
    assert prior_comparison({"full": {"test": full}}) == {}
