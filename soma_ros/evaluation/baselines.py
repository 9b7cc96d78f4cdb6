"""Models the evaluation rolls out side by side: the trained simulator, its baselines and ablations.

Every model is a :class:`RolloutModel`: given an episode (its recorded robot
actions), the episode's initial splats (G_0 aligned to its first frame, the
same for every model) and the scene (gravity, table, dt), it yields the splat
means and covariances of every frame, open loop, frame 0 first.

==============  ======================================================================
variant         what it is (how it is trained: :mod:`soma_ros.evaluation.accuracy`)
==============  ======================================================================
full            the SoMA simulator, trained with ``soma train`` (masked image loss +
                momentum regulariser, two-stage multi-resolution schedule)
prior_only      ``full``'s kept checkpoint with the network's contribution switched off
                (:meth:`~soma_ros.core.simulator.Simulator.set_network`): its physical terms
                (robot coupling, support, physics prior; as trained) alone. Not trained
                itself: what ``full`` beats it by is what the learned network adds
static          the splats never move (no training): the floor every model must beat
state_only      GausSim-style: the same simulator without the ``robot`` effect, so it
                predicts from past states only; since the initial state is the static
                equilibrium by construction (the simulator's ``reference="initial"``),
                a model with gravity and support alone could never move, so it gets the
                effect registry's learnable constant acceleration field (``wind``) as its
                autonomous driving term. Rolled out without actions.
spring_mass     PhysTwin-style physics: :mod:`soma_ros.core.spring_mass` (springs over
                splat nodes, the gripper attached by springs) with five physical
                parameters fitted by gradient on the training bags (:func:`fit_spring_mass`)
img_only        ``full`` without the regulariser (momentum weight 0)
no_mrt          ``full`` without the multi-resolution schedule: every epoch at the frame
                rate on windows (stage 2 only, same number of iterations)
==============  ======================================================================

Persistence: a simulator is a core checkpoint (``checkpoint.pt``); a fitted
spring-mass model is ``spring_mass.pt`` (:meth:`SpringMass.to_payload`, loadable
with ``torch.load(weights_only=True)``); ``static`` needs only a scene.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterable, Iterator, Optional

import numpy as np
import torch

from soma_ros.core.checkpoint import (atomic_torch_save, check_checkpoint_payload, content_checksum,
                                     simulator_from_payload, verify_checksum)
from soma_ros.core.simulator import SceneContext, Simulator
from soma_ros.core.splats import Splats
from soma_ros.core.spring_mass import SpringMass, SpringMassConfig

from soma_ros.data.dataset import EpisodeData

__all__ = [
    "VARIANTS",
    "RolloutModel",
    "StaticModel",
    "SimulatorModel",
    "SpringMassModel",
    "SpringMassFitConfig",
    "fit_spring_mass",
    "observed_points",
    "load_model",
    "save_spring_mass",
    "SPRING_MASS_FILE",
]

#: the variants of the accuracy table, in table order
VARIANTS: tuple[str, ...] = ("full", "prior_only", "static", "state_only", "spring_mass", "img_only", "no_mrt")
SPRING_MASS_FILE = "spring_mass.pt"
SPRING_MASS_FORMAT = "soma_ros.spring_mass/1"

Frame = tuple[torch.Tensor, torch.Tensor]  # (means [N, 3], covs [N, 3, 3])


class RolloutModel:
    """Interface: ``rollout(ep, init, scene)`` yields (means [N, 3], covs [N, 3, 3]) for frames
    0..T-1 of the episode (frame 0 = ``init``), open loop under the episode's actions."""

    kind: str = "model"

    def rollout(self, ep: EpisodeData, init: Splats, scene: SceneContext) -> Iterator[Frame]:  # pragma: no cover
        raise NotImplementedError

    def describe(self) -> dict:
        return {"kind": self.kind}

    def to(self, device) -> "RolloutModel":
        """Run rollouts on ``device`` where the model computes anything (default: nothing to move)."""
        return self


class StaticModel(RolloutModel):
    """The splats never move."""

    kind = "static"

    def rollout(self, ep: EpisodeData, init: Splats, scene: SceneContext) -> Iterator[Frame]:
        means, covs = init.means.detach(), init.covariances().detach()
        for _ in range(ep.num_frames):
            yield means, covs


class SimulatorModel(RolloutModel):
    """A trained :class:`Simulator` rolled out at the frame rate from the episode's initial state,
    under the recorded actions (as :func:`soma_ros.training.train.rollout_full`), or without actions
    (``use_actions=False``; automatic for a model without the ``robot`` effect)."""

    kind = "simulator"

    def __init__(self, sim: Simulator, use_actions: Optional[bool] = None, name: str = "") -> None:
        self.sim = sim.eval()
        has_robot = sim.effects.robot_reach() is not None  # a term the robot drives (robot, physics)
        self.use_actions = has_robot if use_actions is None else bool(use_actions)
        self.name = name

    def to(self, device) -> "SimulatorModel":
        self.sim.to(device)
        return self

    def rollout(self, ep: EpisodeData, init: Splats, scene: SceneContext) -> Iterator[Frame]:
        sim = self.sim
        dev, dt_ = sim.device, sim.dtype
        ctx = SceneContext(scene.gravity, scene.plane_normal, scene.plane_offset, ep.dt).to(device=dev, dtype=dt_)
        with torch.no_grad():
            state = sim.init_state(init.to(device=dev, dtype=dt_), ctx)
            yield state.means, state.covs
            for t in range(1, ep.num_frames):
                action = ep.action(t, dt_, dev) if self.use_actions else None
                state = sim.step(state, action)
                yield state.means, state.covs

    def describe(self) -> dict:
        extra = getattr(self.sim, "checkpoint_extra", {}) or {}
        return {"kind": self.kind, "effects": [e.instance_key for e in self.sim.config.effects],
                "network": bool(self.sim.network_enabled), "use_actions": self.use_actions, "iteration": extra.get("iteration"),
                "complete": extra.get("complete"), "train_config": extra.get("train_config")}


class SpringMassModel(RolloutModel):
    """A fitted :class:`SpringMass`; splats follow its nodes by skinning."""

    kind = "spring_mass"

    def __init__(self, model: SpringMass, info: Optional[dict] = None) -> None:
        self.model = model.eval()
        self.info = dict(info or {})

    def rollout(self, ep: EpisodeData, init: Splats, scene: SceneContext) -> Iterator[Frame]:
        ctx = SceneContext(scene.gravity, scene.plane_normal, scene.plane_offset, ep.dt)
        with torch.no_grad():
            sme = self.model.init_episode(init, ctx)
            nodes = self.model.rollout(sme, ep.actions(range(ep.num_frames)))
            for t in range(ep.num_frames):
                yield self.model.carry(sme, nodes[t])

    def describe(self) -> dict:
        return {"kind": self.kind, "parameters": self.model.describe(), **self.info}


# --------------------------------------------------------------------------- spring-mass fitting
@dataclass
class SpringMassFitConfig:
    """Fitting of the spring-mass parameters (Adam on the five parameters).

    Loss per episode: the mean over frames 1..T-1 (every ``frame_stride``-th) of the mean distance
    from each observed object point (masked depth, robot pixels excluded, at most ``max_points``
    per frame, all cameras) to the nearest simulated splat: the one-sided Chamfer distance
    observed -> simulated (the observation is partial, so the other direction would punish
    occluded splats). ``episodes_per_iter`` training episodes per Adam step.
    """

    iters: int = 40
    lr: float = 0.15
    episodes_per_iter: int = 1
    max_points: int = 1500
    frame_stride: int = 1
    seed: int = 0
    model: SpringMassConfig = field(default_factory=SpringMassConfig)

    def validate(self) -> "SpringMassFitConfig":
        if self.iters < 0 or self.episodes_per_iter < 1 or self.max_points < 1 or self.frame_stride < 1:
            raise ValueError("SpringMassFitConfig: iters >= 0, episodes_per_iter, max_points, frame_stride >= 1")
        if not self.lr > 0:
            raise ValueError("SpringMassFitConfig.lr must be > 0")
        self.model.validate()
        return self


def observed_points(ep: EpisodeData, t: int, max_points: int, generator: torch.Generator) -> torch.Tensor:
    """Object points of frame t from every camera's masked depth (object, not robot), sim frame,
    a random subset of at most ``max_points`` [K, 3] float32."""
    pts, _ = ep.object_points([t])
    if len(pts) > max_points:
        idx = torch.randperm(len(pts), generator=generator)[:max_points]
        pts = pts[idx]
    return pts.float()


def _one_sided_chamfer(obs: torch.Tensor, pred: torch.Tensor) -> torch.Tensor:
    return torch.cdist(obs, pred).min(dim=1).values.mean()


def fit_spring_mass(
    episodes: Iterable[tuple[EpisodeData, Splats]],
    scene: SceneContext,
    cfg: SpringMassFitConfig,
    progress: bool = True,
    log: Callable[[str], None] = print,
) -> tuple[SpringMass, dict]:
    """Fit the spring-mass parameters on training episodes: an iterable of (episode, initial splats),
    consumed once (a generator may load them one by one).

    Returns (the model with the final parameters, info with the loss history, the loss of the
    final parameters over all training episodes, the parameters and the time taken).
    """
    cfg.validate()
    t_start = time.time()
    torch.manual_seed(cfg.seed)
    gen = torch.Generator().manual_seed(cfg.seed)
    model = SpringMass(cfg.model)
    prepared = []
    for ep, init in episodes:
        ctx = SceneContext(scene.gravity, scene.plane_normal, scene.plane_offset, ep.dt)
        sme = model.init_episode(init, ctx)
        frames = list(range(cfg.frame_stride, ep.num_frames, cfg.frame_stride))
        obs = {t: observed_points(ep, t, cfg.max_points, gen) for t in frames}
        frames = [t for t in frames if len(obs[t]) > 0]
        # keep only what the loss needs (an EpisodeData of the paper preset holds ~1.6 GB of images)
        prepared.append((ep.name, sme, frames, obs, ep.actions(range(ep.num_frames))))
    if not prepared:
        raise ValueError("fit_spring_mass: no training episodes")

    def episode_loss(item) -> torch.Tensor:
        _name, sme, frames, obs, actions = item
        last = max(frames) if frames else 0
        nodes = model.rollout(sme, actions[: last + 1])
        losses = [_one_sided_chamfer(obs[t], model.carry(sme, nodes[t], rotations=False)[0]) for t in frames]
        return torch.stack(losses).mean()

    opt = torch.optim.Adam(model.parameters(), lr=cfg.lr)
    rng = np.random.default_rng(cfg.seed)
    history: list[dict] = []
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=cfg.iters, desc="fit spring_mass", unit="it", leave=False, dynamic_ncols=True)
    for it in range(cfg.iters):
        pick = rng.choice(len(prepared), size=min(cfg.episodes_per_iter, len(prepared)), replace=False)
        loss = torch.stack([episode_loss(prepared[int(i)]) for i in pick]).mean()
        if not torch.isfinite(loss):
            raise RuntimeError(f"fit_spring_mass: non-finite loss at iteration {it}")
        opt.zero_grad()
        loss.backward()
        opt.step()
        history.append({"iteration": it + 1, "loss": float(loss.detach()), "episodes": [prepared[int(i)][0] for i in pick],
                        **model.describe()})
        if bar is not None:
            bar.update(1)
            bar.set_postfix(loss=f"{float(loss):.5f}")
    if bar is not None:
        bar.close()
    # the loss of the final parameters on every training episode
    with torch.no_grad():
        final = float(torch.stack([episode_loss(p) for p in prepared]).mean())
    info = {"loss_final_all_train": final, "history": history, "parameters": model.describe(),
            "train_episodes": [p[0] for p in prepared], "seconds": round(time.time() - t_start, 1)}
    log(f"spring_mass: fitted in {info['seconds']:.0f} s, training loss {final:.5f} m, parameters "
        + ", ".join(f"{k}={v:.3g}" for k, v in model.describe().items()))
    return model, info


def save_spring_mass(path: Path, model: SpringMass, info: Optional[dict] = None) -> Path:
    """Write a fitted spring-mass model atomically (weights-only loadable), with a content checksum
    that :func:`load_model` verifies."""
    path = Path(path)
    extra = {k: v for k, v in (info or {}).items() if k != "history"}
    payload = model.to_payload(_plain(extra))
    payload["checksum"] = content_checksum(payload)
    atomic_torch_save(payload, path)
    return path


def _plain(x):
    if isinstance(x, dict):
        return {str(k): _plain(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_plain(v) for v in x]
    if isinstance(x, (np.floating, np.integer)):
        return x.item()
    return x


def load_model(path: str | Path, network: bool = True) -> RolloutModel:
    """A simulator checkpoint (``checkpoint.pt``), a spring-mass file (``spring_mass.pt``), or a run
    folder holding one of them -> :class:`RolloutModel`.

    ``network=False``: the ``prior_only`` baseline -- the same simulator with the network's
    contribution switched off (:meth:`~soma_ros.core.simulator.Simulator.set_network`): its physical
    terms (as trained) alone, so that a table shows what the learned network adds (a ValueError
    for a spring-mass file, which has no network)."""
    p = Path(path)
    if p.is_dir():
        for name in ("checkpoint.pt", SPRING_MASS_FILE):
            if (p / name).is_file():
                p = p / name
                break
        else:
            raise FileNotFoundError(f"{path}: no checkpoint.pt or {SPRING_MASS_FILE} in this folder")
    if not p.is_file():
        raise FileNotFoundError(f"checkpoint not found: {p}")
    try:
        payload = torch.load(p, map_location="cpu", weights_only=True)
    except Exception as exc:
        raise ValueError(f"{p}: not a readable checkpoint ({type(exc).__name__}: {exc})") from None
    fmt = payload.get("format") if isinstance(payload, dict) else None
    if fmt == SPRING_MASS_FORMAT:
        if not network:
            raise ValueError(f"{p}: a spring-mass model has no network to switch off (prior_only needs a simulator "
                             "checkpoint)")
        verify_checksum(payload, p, "spring-mass model")
        return SpringMassModel(SpringMass.from_payload(payload), payload.get("extra", {}))
    check_checkpoint_payload(payload, p)  # the simulator format, with a clear error
    return SimulatorModel(simulator_from_payload(payload, p).set_network(network))
