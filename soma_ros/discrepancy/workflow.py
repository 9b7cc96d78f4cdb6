"""`soma discrepancy`: find where a model and measured data disagree, name the missing effect,
add it to the model and show the gap shrink (issue #8).

    soma discrepancy --checkpoint RUN/checkpoint.pt --data MEASURED --out DIR [--config default]

Steps (every one uses only the measured bags and the model; the evaluation-only
ground truth -- ``/world/object_points``, the ``.meta.json`` sidecars -- is never
read by the decision; Chamfer in the before/after gap is the one exception and
is computed by the evaluation engineer's scorer, :mod:`soma_ros.evaluation.evaluate`):

1. **Resimulate** every measured episode open loop (initial state: G_0 of the
   run's scene aligned to the episode's frame 0, as training and evaluation do)
   and locate the disagreement: per frame and camera the depth RMSE and PSNR
   on object pixels (the eval protocol's :func:`score_frame`, no LPIPS), and the
   3D residual = mean distance from each observed object point (masked depth of
   all cameras back-projected, :meth:`EpisodeData.object_points`) to the nearest
   simulated splat.
2. **Residual motion per cluster**: each observed point is assigned to its
   nearest simulated splat, hence to that splat's fine cluster (hierarchy level
   1); the mean of (observed - simulated) over a cluster's points is that
   cluster's residual displacement at that frame ([T, K, 3] per episode; plots
   of where and when).
3. **Candidate ranking**: for each candidate effect of the library (wind,
   linear/quadratic drag, table friction, gripper slip, mass scale) a copy of
   the model gets the term as a *direct* effect (``direct`` in the config,
   default true: its force is integrated by the simulator on top of the learned
   dynamics as well as fed to the network, see :mod:`soma_ros.core.simulator`;
   a network trained without the term barely responds to it as a feature
   alone) (zero-initialised: nothing changes until fitted) and
   ONLY its parameters are fitted by Adam through the simulator on the *fit*
   episodes (3D point residual loss, full open-loop rollouts; each parameter's
   step is ``fit_lr`` times its typical magnitude, ``Effect.fit_scale``, e.g. |g|
   for a force field, decayed by a cosine to ``fit_lr_final`` of it). On the
   *held-out* episodes, explained = 1 - sum residual_with / sum residual_without
   (per (episode, frame) 3D residual). Uncertainty: a hierarchical bootstrap
   (episodes, then frames within each) with all candidates on the same
   resamples (paired).
   **Own-error control**: a fitted term can also remove the model's own error,
   which is there on any data (a model that under-lifts is "missing" a tighter
   grip everywhere). So each candidate is first *calibrated*: fitted on episodes
   of the conditions the model was trained in (``reference_data``; default: the
   checkpoint's training dataset), then re-fitted from there on the measured fit
   episodes, and explained = 1 - residual(re-fitted) / min(residual(calibrated),
   residual(unchanged), residual(calibration continued on the reference for the
   re-fit's number of steps)) on the held-out episodes: only what the new data asks of
   the term beyond the model's own conditions counts, in either direction (a grip
   that slips on a model that under-lifts too). Without reference data a candidate starts at 0
   and explained is against the unchanged model. The winner is named when the
   lower confidence bound (quantile ``alpha``) of its explained fraction exceeds
   ``min_explained`` AND the lower bound of (winner - runner-up) exceeds 0; else
   ``none``. After each fit, a line search on the whole fit set along the fitted
   change (scales ``line_search`` and 0) keeps the best scale, so a fit that
   does not lower the fit episodes' residual changes nothing.
   All rollouts run the simulator's passive-object rule (``passive_friction``,
   as the live node does): the learned dynamics cannot push a resting object,
   and a candidate's push on it must beat the table's friction. Except
   (``passive_exempt_trained``) on steps where a term the model was trained with
   acts (its robot coupling) with the gripper closed (``passive_exempt_closed``, as
   the live node): there the model is inside its training data, where
   no such rule acted, and the rule's friction on top of the learned drag doubled
   the rope's resimulated held-out Chamfer (9.0 -> 17.3 mm, docs/discrepancy.md).
4. **Add** the named term to the model (its fitted parameters; optional joint
   re-fit on all measured fit episodes), save DIR/model/checkpoint.pt (a run
   folder: checkpoint, scene, train_config.yaml, usable by ``soma eval``), and
   score before/after on the held-out episodes with :func:`evaluate_models`
   (depth RMSE, PSNR, SSIM, AbsRel, Chamfer) plus the workflow's own 3D residual.
5. **Report**: DIR/report.md, DIR/report.json (named_effect, ranking,
   gap_before, gap_after, ...), plots (see :mod:`soma_ros.discrepancy.report`).

The threshold: ``min_explained`` (default 0.1) is a practical-significance floor,
set before any test: a term fitted on other episodes that does not remove at
least a tenth of the held-out disagreement is not worth a model change (and a
term that only absorbs the model's own noise cannot do so systematically on
held-out episodes). The confidence level ``alpha`` = 0.05 (one-sided).
"""

from __future__ import annotations

import copy
import dataclasses
import itertools
import json
import math
import multiprocessing as mp
import os
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Optional, Sequence

import numpy as np
import torch

from soma_ros.core.config import read_config
from soma_ros.paths import config_dir
from soma_ros.core.checkpoint import read_checkpoint, save_checkpoint, load_checkpoint
from soma_ros.core.effects import EFFECTS
from soma_ros.core.render import render
from soma_ros.core.simulator import SceneContext, SimulationDiverged, Simulator
from soma_ros.core.splats import Splats

from soma_ros.training.config import load_train_config, search_past_edge
from soma_ros.data.dataset import EpisodeData
from soma_ros.core.scoring import EvalMetricsConfig, score_frame, table_depth

__all__ = ["DiscrepancyConfig", "load_discrepancy_config", "run_discrepancy", "DEFAULT_CANDIDATES",
           "EpisodeObs", "point_residual", "bootstrap_explained", "decide", "rank_candidates",
           "fit_effect", "residual_per_frame", "episode_residuals",
           "beyond_reference_tail"]

DEFAULT_CANDIDATES = ["wind", "linear_drag", "quadratic_drag", "table_friction", "gripper_slip", "mass_scale",
                      "stiffness_scale"]
CONFIG_DIR = config_dir() / "discrepancy"


@dataclass
class DiscrepancyConfig:
    candidates: list[str] = field(default_factory=lambda: list(DEFAULT_CANDIDATES))
    heldout_split: str = "stratified"  # held-out episodes: "stratified" (heldout_fraction of every task's
    # episodes, evenly spaced: every task is held out) or a manifest split name (the rest are fit episodes)
    heldout_fraction: float = 0.3
    max_points: int = 256  # observed points per frame (evenly strided subset)
    frame_stride: int = 2  # frames scored / used in the 3D loss
    fit_iters: int = 24  # Adam steps per candidate (one fit episode per step, cycling)
    fit_lr: float = 0.05  # Adam step, times each parameter's Effect.fit_scale (its typical magnitude)
    fit_lr_final: float = 0.1  # cosine decay of the step to this fraction over fit_iters
    line_search: list[float] = field(default_factory=lambda: [0.25, 0.5, 1.0, 1.5])  # scales of the fitted
    # parameters tried on the whole fit set (0, the unchanged model, always is)
    line_search_extend: int = 0  # a best scale that is the list's smallest or largest: up to this many more
    # beyond it, with that end's ratio, while each lowers the residual (0: the list only; physics.yaml sets 3)
    passive_friction: Optional[float] = 0.5  # the simulator's passive-object rule in every rollout, as the
    # live node runs it (friction coefficient); None: the checkpoint's setting; < 0: off
    passive_exempt_trained: bool = True  # the terms the model was trained with (its robot coupling) make a
    # step non-passive (DynamicsConfig.passive_exempt); candidates added by the workflow never do
    passive_exempt_closed: bool = True  # ... only while the gripper is closed (DynamicsConfig.passive_exempt_closed),
    # as the live node does (an open gripper's coupling drags, it does not carry)
    max_fit_episodes: int = 0  # 0 = all
    max_heldout_episodes: int = 0  # 0 = all
    bootstrap: int = 2000
    alpha: float = 0.05  # one-sided: the lower bound is the alpha quantile
    min_explained: float = 0.1
    grid_start: list[float] = field(default_factory=list)  # before Adam: try the start value plus these
    # multiples of each parameter's typical magnitude (Effect.fit_scale), one parameter element at a time,
    # and start from the best on grid_episodes fit episodes (a response that stays flat until a threshold,
    # e.g. a grip that holds until it slips, gives Adam no gradient to follow from 0); empty = off
    grid_episodes: int = 4
    grid_refine: int = 0  # after the grid: each element the grid moved from its start also tries the start plus
    # 1/2, 1/4, ... 1/2^grid_refine of that move (one element at a time): a threshold response (a grip that lets go
    # above a load) gives Adam no gradient, and its best value may lie below the grid's first multiple; 0 = off
    grid_joint: int = 2  # effects with at most this many acting parameter elements are gridded jointly (every
    # combination; a grip that slips at a load and one that sags act together, and one element at a time
    # stops where either hides the other); larger ones one element at a time (a wind's 3 components)
    direct: bool = True  # candidates are added as direct effects (explicitly integrated force); False: feature only
    reference_data: Optional[str] = None  # the own-error control (rank_candidates): episodes of the conditions the
    # model was trained in that it was not trained on; None: the checkpoint's training dataset, its non-train
    # episodes; "" or "none": no control
    reference_episodes: int = 12  # episodes of it used (evenly spaced), 0 = all: the calibration and the
    # detection of a discrepancy beyond the model's own error (detect_discrepancy) both use them
    eval_frame_stride: int = 2
    contact_sheets: bool = True
    seed: int = 0
    jobs: int = 1  # candidates fitted in parallel worker processes (spawned, one torch thread each; CPU models);
    # the results do not depend on it
    load_channel: bool = True  # where every measured and reference episode has /joint_states efforts: rank the
    # candidates by the held-out 3D residual's explained fraction plus that of the wrist load (rank_candidates)
    load_in_fit: bool = True  # ... and fit them on both as well (FitObjective): the fit minimises what the
    # ranking scores, each channel relative to the fit's start; where an episode has no efforts, the 3D residual alone

    def validate(self) -> "DiscrepancyConfig":
        unknown = [c for c in self.candidates if c not in EFFECTS]
        if unknown:
            raise ValueError(f"unknown candidate effect(s) {unknown}; registered: {', '.join(sorted(EFFECTS))}")
        if not self.candidates:
            raise ValueError("discrepancy: at least one candidate effect is needed")
        if self.max_points < 8 or self.frame_stride < 1 or self.fit_iters < 0 or self.bootstrap < 100:
            raise ValueError("discrepancy: max_points >= 8, frame_stride >= 1, fit_iters >= 0, bootstrap >= 100 required")
        if not (0 < self.heldout_fraction < 1):
            raise ValueError(f"discrepancy: heldout_fraction must be in (0, 1), got {self.heldout_fraction}")
        if any(not (a > 0) for a in self.line_search):
            raise ValueError(f"discrepancy: line_search scales must be > 0, got {self.line_search}")
        if isinstance(self.line_search_extend, bool) or not isinstance(self.line_search_extend, int) \
                or self.line_search_extend < 0:
            raise ValueError(f"discrepancy: line_search_extend must be an integer >= 0, got {self.line_search_extend!r}")
        if not (0 < self.alpha < 0.5) or not (self.fit_lr > 0) or not (0 < self.fit_lr_final <= 1):
            raise ValueError("discrepancy: alpha in (0, 0.5), fit_lr > 0 and fit_lr_final in (0, 1] required")
        if self.jobs < 1:
            raise ValueError(f"discrepancy: jobs must be >= 1, got {self.jobs}")
        if self.grid_episodes < 1 or self.grid_joint < 1 or any(not math.isfinite(float(k)) for k in self.grid_start):
            raise ValueError("discrepancy: grid_episodes >= 1, grid_joint >= 1 and finite grid_start multiples required")
        if not 0 <= self.grid_refine <= 20:
            raise ValueError(f"discrepancy: grid_refine must be in [0, 20], got {self.grid_refine}")
        return self


def load_discrepancy_config(name_or_path: str = "default", overrides: Optional[dict] = None) -> DiscrepancyConfig:
    """config/discrepancy/<name>.yaml or a YAML path -> :class:`DiscrepancyConfig`."""
    p = Path(name_or_path)
    if not p.is_file():
        p = CONFIG_DIR / f"{name_or_path}.yaml"
    if not p.is_file():
        known = sorted(x.stem for x in CONFIG_DIR.glob("*.yaml"))
        raise FileNotFoundError(f"discrepancy config '{name_or_path}' not found (known: {', '.join(known)})")
    data = read_config(p)
    data.update(overrides or {})
    names = {f.name for f in dataclasses.fields(DiscrepancyConfig)}
    bad = sorted(set(data) - names)
    if bad:
        raise ValueError(f"{p.name}: unknown key(s) {bad} (known: {', '.join(sorted(names))})")
    return DiscrepancyConfig(**data).validate()


# --------------------------------------------------------------------------- per-episode observations
@dataclass
class EpisodeObs:
    """What the workflow keeps of one measured episode: actions, initial splats and the
    observed object points of the scored frames (never the ground truth)."""

    name: str
    task: Optional[str]
    split: str
    dt: float
    control_points: torch.Tensor  # [T, P, 3]
    gripper: torch.Tensor  # [T]
    init: Splats
    frames: list[int]  # scored frames (>= 1)
    points: list[torch.Tensor]  # per scored frame [M, 3]
    #: per scored frame [F] the measured vertical wrist load, N (> 0: the object pulls the hand down;
    #: from the arm's external joint torques, EpisodeData.wrist_force), or None without efforts
    load: Optional[np.ndarray] = None

    @property
    def num_frames(self) -> int:
        return int(self.control_points.shape[0])


def _observed(ep: EpisodeData, t: int, max_points: int) -> torch.Tensor:
    p, _ = ep.object_points([t])
    if len(p) > max_points:
        p = p[torch.linspace(0, len(p) - 1, max_points).round().long()]
    return p.float()


def episode_obs(ctx, ref, cfg: DiscrepancyConfig) -> tuple[EpisodeObs, EpisodeData]:
    """The workflow's view of one episode of an :class:`~soma_ros.evaluation.evaluate.EvalContext` (and the episode)."""
    ep = ctx.store.episode(ref.name)
    frames = list(range(cfg.frame_stride, ep.num_frames, cfg.frame_stride))
    load = None
    if ep.wrist_force is not None:
        g = ctx.scene.gravity.double()
        load = (ep.wrist_force[frames].double() @ (g / g.norm())).numpy()  # [F] N, along gravity
    ob = EpisodeObs(ref.name, ref.task, ref.split, float(ep.dt), ep.control_points.float().clone(),
                    ep.gripper.float().clone(), ctx.store.initial_splats(ref.name), frames,
                    [_observed(ep, t, cfg.max_points) for t in frames], load)
    return ob, ep


HELDOUT = "discrepancy_heldout"  # split label of the held-out episodes in the workflow's evaluation context


def heldout_names(refs, cfg: DiscrepancyConfig) -> list[str]:
    """Names of the held-out episodes (``cfg.heldout_split``, see :class:`DiscrepancyConfig`). Stratified:
    per task (manifest order), round(heldout_fraction * n) of its n episodes, at least one when n >= 2,
    evenly spaced -- a random split can hold out one task only (10 cloth episodes, seed 0: three lifts),
    and an effect that shows in another task would then be invisible on the held-out episodes."""
    if cfg.heldout_split != "stratified":
        return [r.name for r in refs if r.split == cfg.heldout_split]
    by_task: dict = {}
    for r in refs:
        by_task.setdefault(r.task, []).append(r.name)
    out: list[str] = []
    for names in by_task.values():
        n = len(names)
        k = min(n - 1, max(1, int(round(cfg.heldout_fraction * n)))) if n >= 2 else 0
        if k:
            pick = np.round((np.arange(k) + 0.5) * n / k - 0.5).astype(int)
            out += [names[int(i)] for i in pick]
    chosen = set(out)
    return [r.name for r in refs if r.name in chosen]


def mark_heldout(ctx, cfg: DiscrepancyConfig) -> None:
    """Relabel an evaluation context's episodes: split HELDOUT for :func:`heldout_names`, the rest
    "discrepancy_fit" (the evaluation then scores the split HELDOUT; the store looks episodes up by name)."""
    hold = set(heldout_names(ctx.refs, cfg))
    ctx.refs = [dataclasses.replace(r, split=HELDOUT if r.name in hold else "discrepancy_fit") for r in ctx.refs]


def reference_dataset(cfg: DiscrepancyConfig, extra: dict) -> tuple[Optional[Path], bool]:
    """(dataset of the own-error control or None, whether it is the model's training dataset):
    ``cfg.reference_data``, else the checkpoint's training dataset (``extra["dataset"]``) when
    it exists (then only its episodes outside the train split are used: on the episodes it was
    trained on, a model is more accurate than on any new ones, which would make every new
    episode look like it has something missing)."""
    if cfg.reference_data is not None:
        if cfg.reference_data.strip().lower() in ("", "none"):
            return None, False
        p = Path(cfg.reference_data)
        if not (p / "manifest.json").is_file():
            raise FileNotFoundError(f"reference_data {p}: no manifest.json (a dataset of `soma world` / `soma capture`?)")
        return p, False
    d = extra.get("dataset")
    if not d or not (Path(d) / "manifest.json").is_file():
        return None, False
    return Path(d), True


def load_model(checkpoint: Path, cfg: "DiscrepancyConfig") -> Simulator:
    """The unchanged model of a checkpoint with the workflow's passive-object rule, in eval mode."""
    sim = load_checkpoint(checkpoint)
    return sim.set_passive_friction(cfg.passive_friction, sim.trained_terms() if cfg.passive_exempt_trained else None,
                                    cfg.passive_exempt_closed).eval()


def point_residual(points: torch.Tensor, means: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(mean distance [] from each observed point to its nearest splat, nearest index [M],
    residual vectors observed - nearest [M, 3]); differentiable in ``means``."""
    if len(points) == 0:
        z = means.new_zeros(())
        return z, torch.zeros(0, dtype=torch.long), means.new_zeros((0, 3))
    d = torch.cdist(points.to(means), means)
    dist, idx = d.min(dim=1)
    return dist.mean(), idx, points.to(means) - means[idx]


def _scene(base: SceneContext, dt: float, sim: Simulator) -> SceneContext:
    return SceneContext(base.gravity, base.plane_normal, base.plane_offset, dt).to(device=sim.device, dtype=sim.dtype)


def _rollout(sim: Simulator, ob: EpisodeObs, scene: SceneContext, keep: Sequence[int]):
    """Open-loop rollout from frame 0; yields (t, state) for t in ``keep`` (differentiable)."""
    keep = set(keep)
    state = sim.init_state(ob.init.to(device=sim.device, dtype=sim.dtype), _scene(scene, ob.dt, sim))
    from soma_ros.core.simulator import RobotAction

    for t in range(1, max(keep) + 1):
        state = sim.step(state, RobotAction(ob.control_points[t].to(sim.device, sim.dtype),
                                            ob.gripper[t].to(sim.device, sim.dtype)))
        if t in keep:
            yield t, state


def predicted_load(sim: Simulator, mass: torch.Tensor, means: torch.Tensor, gripper: float,
                   scene: SceneContext) -> float:
    """:func:`load_tensor` as a float (N)."""
    return float(load_tensor(sim, mass, means, gripper, scene).detach())


def load_tensor(sim: Simulator, mass: torch.Tensor, means: torch.Tensor, gripper: float,
                scene: SceneContext) -> torch.Tensor:
    """[] The vertical load (N) that a simulated state puts on a closed gripper, quasi-statically: the
    weight of the object's part off the table (each splat's mass [N] times the mass term's band of
    height above the table, 0 below 2 cm, 1 above 5 cm, at ``means`` [N, 3]) times the model's
    :meth:`~soma_ros.core.effects.EffectSet.weight_factor`; 0 with the gripper open (``gripper`` c
    > 0.5). Inertia and the table's share of a rope's tension near it are left out: the same for
    every candidate, so the comparison of candidates does not hinge on them. Differentiable in ``means``
    and in the mass term's parameter."""
    assert mass.shape == means.shape[:1] and means.shape[-1] == 3, (mass.shape, means.shape)
    if float(gripper) > 0.5:
        return means.new_zeros(())
    from soma_ros.core.effects import smoothstep
    from soma_ros.core.effects.library import MassScale

    band = MassScale.Params()
    n = scene.plane_normal.to(means)
    h = means @ n + float(scene.plane_offset)
    lifted = smoothstep((h - band.d0) / (band.d1 - band.d0))
    g = float(scene.gravity.norm())
    return g * sim.effects.weight_factor(as_tensor=True) * (mass.to(means) * lifted).sum()


@torch.no_grad()
def scores_per_frame(sim: Simulator, ob: EpisodeObs, scene: SceneContext) -> tuple[np.ndarray, Optional[np.ndarray]]:
    """([F] 3D residual (m), [F] |measured - predicted wrist load| (N) or None without efforts) of each
    scored frame of an episode; +inf on every frame of both when the rollout diverges
    (:class:`SimulationDiverged`: a candidate's value that makes the model unstable is the worst
    value, never a crash of the whole workflow)."""
    res, pred = [], []
    mass = ob.init.mass
    try:
        for i, (t, st) in enumerate(_rollout(sim, ob, scene, ob.frames)):
            res.append(float(point_residual(ob.points[i], st.means)[0]))
            if ob.load is not None:
                pred.append(predicted_load(sim, mass, st.means, float(ob.gripper[t]), scene))
    except SimulationDiverged:
        inf = np.full(len(ob.frames), np.inf)
        return inf, (None if ob.load is None else inf.copy())
    return np.asarray(res), (None if ob.load is None else np.abs(np.asarray(ob.load) - np.asarray(pred)))


def residual_per_frame(sim: Simulator, ob: EpisodeObs, scene: SceneContext) -> np.ndarray:
    """[F] 3D residual (m) of each scored frame of an episode (:func:`scores_per_frame`)."""
    return scores_per_frame(sim, dataclasses.replace(ob, load=None), scene)[0]


@dataclass(frozen=True)
class FitObjective:
    """What a candidate's fit minimises per scored frame: the 3D residual (m) plus ``load_weight`` (m/N)
    times the |wrist load error| (N). With ``load_weight`` = the fit start's 3D residual sum over its
    wrist load error sum on the fit's episodes (:func:`objective_at_start`), the objective is, up to that
    constant, the sum of both channels relative to the start, the quantity the ranking scores held out
    (the explained fractions' sum; :func:`decide`). 0: the 3D residual alone."""

    load_weight: float = 0.0

    def per_frame(self, sim: Simulator, ob: EpisodeObs, scene: SceneContext) -> np.ndarray:
        """[F] the objective of each scored frame of an episode (+inf where the rollout diverges); the 3D
        residual alone on an episode without efforts, as :func:`fit_effect`'s steps."""
        if not self.load_weight or ob.load is None:
            return residual_per_frame(sim, ob, scene)
        res, load = scores_per_frame(sim, ob, scene)
        return res + self.load_weight * load

    def total(self, sim: Simulator, obs: Sequence[EpisodeObs], scene: SceneContext) -> float:
        return float(sum(self.per_frame(sim, o, scene).sum() for o in obs))


def objective_at_start(sim: Simulator, obs: Sequence[EpisodeObs], scene: SceneContext, cfg: "DiscrepancyConfig",
                       residual_sum: Optional[float] = None) -> tuple[FitObjective, float]:
    """(the :class:`FitObjective` of a fit that starts at ``sim`` on ``obs``, its value there). With
    ``cfg.load_in_fit`` and efforts in every episode, the wrist load error counts at the start's ratio
    of the two sums (its value there is then twice the 3D residual sum); else the 3D residual alone,
    whose sum ``residual_sum`` is taken as given when the caller has it (no rollout)."""
    if cfg.load_in_fit and obs and all(o.load is not None for o in obs):
        scores = [scores_per_frame(sim, o, scene) for o in obs]
        res = float(sum(r.sum() for r, _ in scores))
        load = float(sum(ld.sum() for _, ld in scores))
        if math.isfinite(res) and math.isfinite(load) and res > 0 and load > 0:
            return FitObjective(res / load), 2.0 * res
        return FitObjective(), res
    if residual_sum is None:
        residual_sum = float(sum(residual_per_frame(sim, o, scene).sum() for o in obs))
    return FitObjective(), residual_sum


# --------------------------------------------------------------------------- statistics
def bootstrap_explained(base: Sequence[np.ndarray], cand: dict[str, Sequence[np.ndarray]], n: int,
                        seed: int = 0) -> dict[str, np.ndarray]:
    """Hierarchical paired bootstrap of explained = 1 - sum(with) / sum(without).

    ``base``: per held-out episode the per-frame residual without the term (one list for every
    candidate), or a dict {name: [alternative baselines, each such a list]}, where the sum
    without the term is the smallest of the alternatives' sums on the resample; ``cand[name]``:
    the same frames with the fitted term. Resamples episodes with replacement, then frames
    within each; every candidate uses the same resamples. Returns {name: [n] samples}."""
    rng = np.random.default_rng(seed)
    bases = base if isinstance(base, dict) else {k: [base] for k in cand}
    any_base = next(iter(bases.values()))[0]
    E = len(any_base)
    out = {k: np.empty(n) for k in cand}
    for b in range(n):
        eps = rng.integers(0, E, E)
        num = {k: 0.0 for k in cand}
        den = {k: [0.0] * len(bases[k]) for k in cand}
        for e in eps:
            f = rng.integers(0, len(any_base[e]), len(any_base[e]))
            for k in cand:
                for j, alt in enumerate(bases[k]):
                    den[k][j] += float(alt[e][f].sum())
                num[k] += float(cand[k][e][f].sum())
        for k in cand:
            d = min(den[k])
            out[k][b] = 1.0 - num[k] / d if d > 0 else 0.0
    return out


def detect_discrepancy(measured: Sequence[float], reference: Sequence[float], n: int, alpha: float,
                       seed: int = 0, min_episodes: int = 3, measured_tasks: Optional[Sequence] = None,
                       reference_tasks: Optional[Sequence] = None) -> dict:
    """Do the measured episodes disagree with the model by more than its own error does?

    ``measured`` / ``reference``: the unchanged model's mean 3D residual of each measured episode
    and of each reference episode (the conditions it was trained in; episodes are the
    independent units). Statistic: AUC = P(a measured episode's residual > a reference one's)
    (+ half the ties), 0.5 when the measured data are like the reference; its lower bound is the
    ``alpha`` quantile of a bootstrap that resamples both groups' episodes. ``detected``: that
    bound is above 0.5; None (not assessed) with fewer than ``min_episodes`` in either group.
    Rank-based, so one episode where the model fails on either side does not decide it. Also the
    ratio of the median residuals (an effect size in the residual's own unit) with its bound.

    With task labels on both sides (``measured_tasks`` / ``reference_tasks``, the manifest's
    ``task``), pairs are formed within a task only: AUC = P(measured > reference) over the
    same-task pairs (a stratified Mann-Whitney statistic), and the bootstrap resamples within
    every task. The model's error differs from task to task far more than an effect moves it
    (rope: lifts 7-10 mm, drags 3-5 mm), so comparing a lift with a drag is mostly noise.
    Episodes of a task the other side does not have are left out (``n_unpaired``)."""
    x = np.asarray(measured, dtype=np.float64)
    y = np.asarray(reference, dtype=np.float64)
    out = {"n_measured": int(x.size), "n_reference": int(y.size), "alpha": alpha,
           "measured_median": float(np.median(x)) if x.size else None,
           "reference_median": float(np.median(y)) if y.size else None}
    tx = list(measured_tasks) if measured_tasks is not None else [None] * x.size
    ty = list(reference_tasks) if reference_tasks is not None else [None] * y.size
    if len(tx) != x.size or len(ty) != y.size:
        raise ValueError(f"detect_discrepancy: {len(tx)} / {len(ty)} task labels for {x.size} / {y.size} episodes")
    if any(t is None for t in tx + ty):  # unlabelled episodes on either side: one stratum
        tx, ty = [None] * x.size, [None] * y.size
    strata = sorted({t for t in tx} & {t for t in ty}, key=str)
    groups = [(x[[i for i, t in enumerate(tx) if t == k]], y[[i for i, t in enumerate(ty) if t == k]]) for k in strata]
    n_x, n_y = sum(g[0].size for g in groups), sum(g[1].size for g in groups)
    out.update(stratified_by_task=strata != [None], tasks=[str(k) for k in strata if k is not None],
               n_unpaired=int(x.size - n_x + y.size - n_y))
    if n_x < min_episodes or n_y < min_episodes:
        return {**out, "assessed": False, "detected": None}

    def pairs_greater(a, b):  # [..., A], [..., B] -> [...]: sum over pairs of 1{a > b} + 0.5 1{a = b}
        d = a[..., :, None] - b[..., None, :]
        return (d > 0).sum((-1, -2)) + 0.5 * (d == 0).sum((-1, -2))

    rng = np.random.default_rng(seed)
    n_pairs = sum(a.size * b.size for a, b in groups)
    a0 = float(sum(pairs_greater(a, b) for a, b in groups) / n_pairs)
    a_bs = np.zeros(n)
    for a, b in groups:
        a_bs += pairs_greater(a[rng.integers(0, a.size, (n, a.size))], b[rng.integers(0, b.size, (n, b.size))])
    a_bs /= n_pairs
    xs = x[rng.integers(0, x.size, (n, x.size))]
    ys = y[rng.integers(0, y.size, (n, y.size))]
    ratio_bs = np.median(xs, axis=1) / np.maximum(np.median(ys, axis=1), 1e-12)
    lo = float(np.quantile(a_bs, alpha))
    return {**out, "assessed": True, "detected": bool(lo > 0.5), "auc": a0, "auc_low": lo,
            "median_ratio": float(np.median(x) / max(float(np.median(y)), 1e-12)),
            "median_ratio_low": float(np.quantile(ratio_bs, alpha))}


def beyond_reference_tail(groups: Sequence[tuple[int, int]], observed: int) -> float:
    """P(at least ``observed`` measured episodes beyond the largest reference residual of their
    group) were every group's measured and reference episodes exchangeable (no effect).

    ``groups``: (k measured, m reference episodes) per group (a task). Within a group the count is
    the number of measured episodes ranked above every reference one in the pooled order, so
    P(X >= j) = C(k, j) / C(k + m, j): the events share the reference's largest and are not
    independent, and a binomial with p = 1 / (m + 1) would overstate the evidence (with 6
    reference episodes per task, 7 of 20 beyond has P 0.076, not the binomial 0.017). Groups are
    independent; their distributions are convolved. Exact; 1.0 with no group."""
    dist = np.array([1.0])
    for k, m in groups:
        if k < 0 or m < 1:
            raise ValueError(f"beyond_reference_tail: need k >= 0 measured and m >= 1 reference episodes, got {k}, {m}")
        n = k + m
        # P(X = j) = P(the top j of the pooled order are measured and the next one is a reference)
        p = [math.comb(k, j) / math.comb(n, j) * m / (n - j) for j in range(k + 1)]
        dist = np.convolve(dist, p)
    return float(min(1.0, dist[observed:].sum())) if observed > 0 else 1.0


def episode_residuals(measured: dict[str, dict], reference: Sequence[tuple]) -> tuple[dict[str, dict], dict]:
    """Every measured episode's place against the model's own error, for the report.

    ``measured``: {episode: {"task", "split", "residual" (mean 3D residual, m), "depth_rmse"}};
    ``reference``: (task, mean 3D residual) of each reference episode. Each episode is compared
    with the reference episodes of its task (all of them where none has that task): it gets
    ``vs_reference_median`` (residual / their median), ``reference_max`` (their largest),
    ``vs_reference_max`` and ``beyond_reference`` (residual > the largest); None / False without
    reference episodes. Returns (episodes worst first, summary): ``count`` beyond the largest,
    ``expected_by_chance`` (sum of 1 / (m + 1), m the number of reference episodes compared with)
    and ``p_value``, the exact probability of at least ``count`` were the data like the reference
    (:func:`beyond_reference_tail`; episodes of tasks the reference lacks form one group against
    all reference episodes, an approximation). An effect that hits only some episodes hard (a rope
    the wind rolls away in 6 of 20) leaves the rank-based detection's bound below 0.5 yet puts
    those episodes far out: this says which they are. Not used by the detection or the naming."""
    by_task: dict = {}
    for task, r in reference:
        by_task.setdefault(task, []).append(float(r))
    every = [r for v in by_task.values() for r in v]
    out, measured_in = {}, {}  # measured episodes per reference pool (a task, or None: every reference)
    for name, m in sorted(measured.items(), key=lambda kv: -kv[1]["residual"]):
        key = m.get("task") if by_task.get(m.get("task")) else None  # None: compared with every reference
        pool = by_task[key] if key is not None else every
        top = max(pool) if pool else None
        med = float(np.median(pool)) if pool else None
        if pool:
            measured_in[key] = measured_in.get(key, 0) + 1
        out[name] = {**m, "reference_median": med, "vs_reference_median": (m["residual"] / med) if med else None,
                     "reference_max": top, "vs_reference_max": (m["residual"] / top) if top else None,
                     "beyond_reference": bool(top is not None and m["residual"] > top)}
    groups = [(k, len(by_task[key] if key is not None else every)) for key, k in measured_in.items()]  # (k, m)
    count = sum(v["beyond_reference"] for v in out.values())
    p_value = beyond_reference_tail(groups, count) if groups else None
    return out, {"count": int(count), "expected_by_chance": float(sum(k / (m + 1) for k, m in groups)),
                 "p_value": p_value}


#: a candidate's wrist-load explained fraction counts at least this much in its score: one that more
#: than doubles the load error contradicts the force measurement, and how badly does not matter
LOAD_FLOOR = -1.0


def decide(explained: dict[str, float], samples: dict[str, np.ndarray], alpha: float,
           min_explained: float, load: Optional[dict[str, float]] = None,
           load_samples: Optional[dict[str, np.ndarray]] = None) -> tuple[str, list[dict], dict]:
    """(named effect or "none", ranking rows sorted by score, decision details).

    Without ``load``: score = the explained fraction of the held-out 3D residual. With ``load`` /
    ``load_samples`` (per candidate the explained fraction of the held-out wrist load error and its
    bootstrap samples, drawn on the same resamples as ``samples``): score = explained + max(load,
    LOAD_FLOOR), the two channels' relative improvements weighted alike. A camera cannot tell a
    heavier object from a softer one (they move alike); the wrist can. The winner (highest score)
    is named when the lower bound of its 3D explained fraction exceeds ``min_explained`` (the gap
    to close is the motion's) and the lower bound of its score's margin over the runner-up's
    exceeds 0."""
    rows = []
    score_samples: dict[str, np.ndarray] = {}
    for k, e in explained.items():
        s = samples[k]
        row = {"name": k, "explained_fraction": float(e), "uncertainty": float(np.std(s)),
               "ci_low": float(np.quantile(s, alpha)), "ci_high": float(np.quantile(s, 1 - alpha)), "score": float(e)}
        score_samples[k] = s
        if load is not None and load_samples is not None:
            ls = np.maximum(load_samples[k], LOAD_FLOOR)
            row.update(load_explained=float(load[k]), load_ci_low=float(np.quantile(ls, alpha)),
                       load_ci_high=float(np.quantile(ls, 1 - alpha)), score=float(e) + max(float(load[k]), LOAD_FLOOR))
            score_samples[k] = s + ls
        rows.append(row)
    rows.sort(key=lambda r: -r["score"])
    if not rows:  # no candidate could be tested (none acts in this model, or all diverged)
        return "none", [], {"alpha": alpha, "min_explained": min_explained, "winner_candidate": None,
                            "winner_lower_bound": float("nan"),
                            "significant": False}
    best = rows[0]
    info = {"alpha": alpha, "min_explained": min_explained, "winner_candidate": best["name"],
            "winner_lower_bound": best["ci_low"], "wrist_load": load is not None and load_samples is not None}
    ok = best["ci_low"] > min_explained
    if len(rows) > 1:
        second = rows[1]
        diff = score_samples[best["name"]] - score_samples[second["name"]]
        info["runner_up"] = second["name"]
        info["margin"] = best["score"] - second["score"]
        info["margin_lower_bound"] = float(np.quantile(diff, alpha))
        ok = ok and info["margin_lower_bound"] > 0
    info["significant"] = bool(ok)
    return (best["name"] if ok else "none"), rows, info


# --------------------------------------------------------------------------- fitting
def _finite_grads(params: Sequence[torch.Tensor]) -> bool:
    """Whether every parameter's gradient is finite (or absent): a step with it can be taken."""
    return all(p.grad is None or bool(torch.isfinite(p.grad).all()) for p in params)


def fit_effect(sim: Simulator, name: str, fit_obs: Sequence[EpisodeObs], scene: SceneContext,
               cfg: DiscrepancyConfig, iters: int, log: Callable[[str], None] = print,
               key: Optional[str] = None, objective: FitObjective = FitObjective()
               ) -> tuple[Simulator, list[float], dict]:
    """A copy of ``sim`` with effect ``name`` added (unless ``key`` names one already there) and
    only that effect's parameters fitted by Adam on ``objective`` over ``fit_obs`` (the 3D point
    residual, plus the wrist load error where it has a weight; one episode per step). The result
    is the mean of the iterates over the second half of the
    steps (Polyak-Ruppert averaging): single-episode gradients are noisy, and the last iterate
    of a sign-normalised optimiser wanders by about a step size per step around the optimum.
    Returns (model, per-step losses, fitted parameter values)."""
    model = copy.deepcopy(sim)
    if key is None:
        model.add_effect({"name": name, "direct": bool(cfg.direct), "fitted_after_training": True})
        key = name
    for p in model.parameters():
        p.requires_grad_(False)
    named = model.acting_parameters(key)  # through a physics prior, or as the term's own force
    params = [p for _, p in named]
    for p in params:
        p.requires_grad_(True)
    model.eval()
    losses: list[float] = []
    if params and iters > 0 and fit_obs and cfg.grid_start:
        _grid_start(model, key, fit_obs, scene, cfg, log, objective)
    if params and iters > 0 and fit_obs:
        scale = getattr(model.effects[key], "fit_scale", {}) or {}
        groups = [{"params": [p], "lr": cfg.fit_lr * float(scale.get(n, 1.0))} for n, p in named]
        opt = torch.optim.Adam(groups, lr=cfg.fit_lr)
        base_lr = [g["lr"] for g in opt.param_groups]
        # cosine decay of every step size to fit_lr_final of its start: big steps to reach a
        # large effect, small ones to settle on it. Set by hand, k = the steps counted so far (a
        # non-finite gradient's step is counted, not taken): torch's LambdaLR warned on every
        # fit whose first gradient was not finite, though the schedule it kept was this one
        decay = lambda k: cfg.fit_lr_final + (1.0 - cfg.fit_lr_final) * 0.5 * (  # noqa: E731
            1.0 + math.cos(math.pi * min(k, iters) / iters))
        counted = 0
        rng = np.random.default_rng(cfg.seed)
        order: list[int] = []
        avg = [torch.zeros_like(p) for p in params]
        n_avg = 0
        for it in range(iters):
            if not order:
                order = list(rng.permutation(len(fit_obs)))
            ob = fit_obs[order.pop()]
            opt.zero_grad()
            weigh_load = bool(objective.load_weight) and ob.load is not None
            try:
                terms = []
                for i, (t, st) in enumerate(_rollout(model, ob, scene, ob.frames)):
                    term = point_residual(ob.points[i], st.means)[0]
                    if weigh_load:
                        pred = load_tensor(model, ob.init.mass, st.means, float(ob.gripper[t]), scene)
                        term = term + objective.load_weight * (pred - float(ob.load[i])).abs()
                    terms.append(term)
            except SimulationDiverged:  # this value is unstable on this episode: no gradient to follow
                losses.append(math.inf)
                continue
            loss = torch.stack(terms).mean()
            losses.append(float(loss.detach()))
            if not loss.requires_grad:
                continue
            loss.backward()
            if _finite_grads(params):
                for g, lr0 in zip(opt.param_groups, base_lr):
                    g["lr"] = lr0 * decay(counted)
                opt.step()
                model.effects[key].project_()  # inside the term's physical range (Effect.bounds)
            counted += 1
            if it >= iters // 2:
                for a, p in zip(avg, params):
                    a.add_(p.detach())
                n_avg += 1
        if n_avg:
            with torch.no_grad():
                for a, p in zip(avg, params):
                    p.copy_(a / n_avg)
    for p in params:
        p.requires_grad_(False)
    model.effects[key].project_()
    return model, losses, _values(model, key)


@torch.no_grad()
def _grid_start(model: Simulator, key: str, fit_obs: Sequence[EpisodeObs], scene: SceneContext,
                cfg: DiscrepancyConfig, log: Callable[[str], None], objective: FitObjective = FitObjective()) -> None:
    """Move effect ``key``'s acting parameters to the best start on a coarse grid
    (``cfg.grid_start``: multiples of each parameter's ``Effect.fit_scale`` added to its value, clamped
    to its bounds; the current values always count), scored by ``objective``'s sum on
    ``cfg.grid_episodes`` evenly spaced fit episodes. Every combination when the effect has at most
    ``cfg.grid_joint`` acting elements, else greedy, one element after another. Then, with
    ``cfg.grid_refine`` = k, every element the grid moved also tries its start plus 1/2, 1/4, ... 1/2^k
    of that move, one element at a time."""
    n = min(len(fit_obs), max(1, cfg.grid_episodes))
    sub = [fit_obs[int(i)] for i in np.round(np.linspace(0, len(fit_obs) - 1, n)).astype(int)]
    score = lambda: objective.total(model, sub, scene)  # noqa: E731
    best = score()
    scale = getattr(model.effects[key], "fit_scale", {}) or {}
    named = model.acting_parameters(key)
    # every acting element: (its flat view, index, the values it may take: its start first)
    elements = []
    for name, p in named:
        lo, hi = model.effects[key].bounds.get(name, (-math.inf, math.inf))
        flat = p.view(-1)
        for i in range(flat.numel()):
            start = float(flat[i])
            values = [start] + [min(max(start + float(k) * float(scale.get(name, 1.0)), lo), hi) for k in cfg.grid_start]
            elements.append((flat, i, list(dict.fromkeys(values))))
    if len(elements) <= cfg.grid_joint:
        best_combo = tuple(v[0] for _, _, v in elements)
        for combo in itertools.product(*(v for _, _, v in elements)):
            if combo == best_combo:
                continue
            for (flat, i, _), v in zip(elements, combo):
                flat[i] = v
            r = score()
            if r < best:
                best, best_combo = r, combo
        for (flat, i, _), v in zip(elements, best_combo):
            flat[i] = v
    else:
        for flat, i, values in elements:
            best_v = values[0]
            for v in values[1:]:
                flat[i] = v
                r = score()
                if r < best:
                    best, best_v = r, v
            flat[i] = best_v
    if cfg.grid_refine:  # towards the start: a small effect may lie below the grid's first step
        for flat, i, values in elements:
            start, best_v = values[0], float(flat[i])
            move = best_v - start  # the grid's move, fixed: each k tries 1/2^k of it, not of a better fraction
            if move == 0:
                continue
            for k in range(1, cfg.grid_refine + 1):
                flat[i] = start + move / 2 ** k
                r = score()
                if r < best:
                    best, best_v = r, float(flat[i])
            flat[i] = best_v
    log(f"    grid start: {', '.join(f'{n_}={p.detach().reshape(-1).tolist()}' for n_, p in named)}")


def _line_search(model: Simulator, name: str, theta0: list[torch.Tensor], obs: Sequence[EpisodeObs],
                 scene: SceneContext, scales: Sequence[float], base: float, extend: int = 0,
                 objective: FitObjective = FitObjective()) -> tuple[float, float]:
    """Set effect ``name``'s parameters to theta0 + a (theta - theta0), theta their fitted values,
    with the scale a in {0} + ``scales`` of the lowest ``objective`` sum on ``obs`` (``base``: at
    a = 0). A fit that does not lower it is undone (a = 0); an over- or undershoot of the
    stochastic fit is corrected. When the best is the smallest or the largest of ``scales``, up to
    ``extend`` more scales beyond it (that end's ratio) are tried while each lowers the sum.
    Returns (a, objective sum)."""
    params = [p for _, p in model.acting_parameters(name)]
    theta = [p.detach().clone() for p in params]

    def score(a: float) -> float:
        with torch.no_grad():
            for p, t, t0 in zip(params, theta, theta0):
                p.copy_(t0 + a * (t - t0))
        model.effects[name].project_()  # an overshoot (a > 1) stays inside the physical range
        return objective.total(model, obs, scene)

    best_a, best = 0.0, base
    for a in scales:
        r = score(a)
        if r < best:
            best_a, best = float(a), r
    best_a, best, _ = search_past_edge(scales, best_a, best, score, extend, logarithmic=True)  # a = 0: not an edge
    with torch.no_grad():
        for p, t, t0 in zip(params, theta, theta0):
            p.copy_(t0 + best_a * (t - t0))
    model.effects[name].project_()
    return best_a, best


def _values(model: Simulator, name: str) -> dict:
    return {n: p.detach().cpu().reshape(-1).tolist() for n, p in model.acting_parameters(name)}


@dataclass
class _CandidateWork:
    """What every candidate's fit reads (shared by the worker processes of ``cfg.jobs``)."""

    sim: Simulator
    fit_obs: list
    held_obs: list
    base: list
    scene: SceneContext
    cfg: "DiscrepancyConfig"
    ref_obs: list
    ref_scene: SceneContext
    start: tuple  # (FitObjective, its value) of the unchanged model on ref_obs (on fit_obs without a reference)
    den0: float
    base_load: Optional[list] = None  # per held-out episode [F] |load error| of the unchanged model (N), or None


def with_effect(sim: Simulator, name: str, values: dict, cfg: "DiscrepancyConfig") -> Simulator:
    """A copy of ``sim`` with effect ``name`` added as the workflow adds a candidate, its acting
    parameters set to ``values`` ({parameter: flat list}, as :func:`fit_effect` returns them) and
    every parameter frozen: the fitted model, rebuilt from its values."""
    model = copy.deepcopy(sim)
    model.add_effect({"name": name, "direct": bool(cfg.direct), "fitted_after_training": True})
    for p in model.parameters():
        p.requires_grad_(False)
    with torch.no_grad():
        for n, p in model.acting_parameters(name):
            p.copy_(torch.as_tensor(values[n], dtype=p.dtype, device=p.device).reshape(p.shape))
    return model.eval()


def fit_candidate(w: _CandidateWork, name: str, log: Callable[[str], None]) -> Optional[dict]:
    """One candidate of :func:`rank_candidates`: calibrated on the reference (when there is one),
    fitted on the measured fit episodes, line-searched, scored on the held-out ones. Returns
    {"rec": its report record, "res": held-out residuals, "base": its baselines}, or None when
    the model gives it no handle or its fitted values diverge held out."""
    sim, fit_obs, held_obs, scene, cfg = w.sim, w.fit_obs, w.held_obs, w.scene, w.cfg
    ref_obs, ref_scene = w.ref_obs, w.ref_scene
    tc = time.time()
    rec: dict = {}
    probe = copy.deepcopy(sim)
    probe.add_effect({"name": name, "direct": bool(cfg.direct)})
    if not probe.acting_parameters(name):  # e.g. stiffness_scale in a model without a physics prior
        log(f"  candidate {name:15s} has no handle in this model (its parameters act only through a physics "
            "prior): not tested")
        return None
    del probe
    if ref_obs:  # calibration on the model's own conditions
        ref_objective, ref_start = w.start
        calib, _, _ = fit_effect(sim, name, ref_obs, ref_scene, cfg, cfg.fit_iters, log, objective=ref_objective)
        zero = [torch.zeros_like(p) for _, p in calib.acting_parameters(name)]
        a, r = _line_search(calib, name, zero, ref_obs, ref_scene, cfg.line_search, ref_start,
                            cfg.line_search_extend, ref_objective)
        rec.update(reference_parameters=_values(calib, name), reference_explained=1.0 - r / max(ref_start, 1e-12),
                   reference_scale=a)
        calib_held = [scores_per_frame(calib, o, scene) for o in held_obs]
        bases = [[r for r, _ in calib_held], list(w.base)]
        load_bases = [[ld for _, ld in calib_held], list(w.base_load or [])]
        objective, fit_start = objective_at_start(calib, fit_obs, scene, cfg)
        model, losses, _ = fit_effect(calib, name, fit_obs, scene, cfg, cfg.fit_iters, log, key=name,
                                      objective=objective)
        theta0 = [p.detach().clone() for _, p in calib.acting_parameters(name)]
        # the same budget on the reference: the re-fit continues an optimisation the calibration
        # may not have finished, and what more steps on *any* data would find is not new
        cont, _, _ = fit_effect(calib, name, ref_obs, ref_scene, cfg, cfg.fit_iters, log, key=name,
                                objective=ref_objective)
        _line_search(cont, name, theta0, ref_obs, ref_scene, cfg.line_search, r,  # as the re-fit's
                     cfg.line_search_extend, ref_objective)
        cont_held = [scores_per_frame(cont, o, scene) for o in held_obs]
        bases.append([r for r, _ in cont_held])
        load_bases.append([ld for _, ld in cont_held])
        rec.update(reference_continued_parameters=_values(cont, name))
    else:
        objective, fit_start = w.start
        model, losses, _ = fit_effect(sim, name, fit_obs, scene, cfg, cfg.fit_iters, log, objective=objective)
        bases = [list(w.base)]
        load_bases = [list(w.base_load or [])]
        theta0 = [torch.zeros_like(p) for _, p in model.acting_parameters(name)]
    best_a, fit_with = _line_search(model, name, theta0, fit_obs, scene, cfg.line_search, fit_start,
                                    cfg.line_search_extend, objective)
    rec["fit_load_weight"] = objective.load_weight
    values = _values(model, name)
    held_scores = [scores_per_frame(model, o, scene) for o in held_obs]
    res = [r for r, _ in held_scores]
    load_res = [ld for _, ld in held_scores] if w.base_load is not None else None
    unstable = [o.name for o, r in zip(held_obs, res) if not np.isfinite(r).all()]
    if unstable:  # stable on the fit episodes (line search), not held out: not a physical explanation
        log(f"  candidate {name:15s} diverges with its fitted values {values} on held-out "
            f"episode(s) {', '.join(unstable)}: not ranked ({time.time() - tc:.0f} s)")
        return None
    den = max(min(sum(float(x.sum()) for x in alt) for alt in bases), 1e-12)
    num = sum(float(x.sum()) for x in res)
    e = 1.0 - num / den
    if load_res is not None:
        lden = max(min(sum(float(x.sum()) for x in alt) for alt in load_bases), 1e-12)
        rec["load_explained"] = max(1.0 - sum(float(x.sum()) for x in load_res) / lden, LOAD_FLOOR)
    at_bound = [n for n in model.effects[name].project_() if n in values]
    if at_bound:
        log(f"  candidate {name:15s} fitted at the edge of its physical range ({', '.join(at_bound)}): the data "
            "ask for more than this term can be")
    rec.update(parameters=values, at_bound=at_bound, fit_loss=losses, explained_fraction=e,
               explained_vs_unchanged=1.0 - num / w.den0, fit_explained=1.0 - fit_with / max(fit_start, 1e-12),
               kept=best_a > 0, line_search_scale=best_a, seconds=round(time.time() - tc, 1))
    msg = (f"  (calibrated {rec['reference_parameters']}, own-data explained {rec['reference_explained']:+.3f}; "
           f"vs unchanged {rec['explained_vs_unchanged']:+.3f})" if ref_obs else "")
    if load_res is not None:
        msg += f"  wrist load explained {rec['load_explained']:+.3f}"
    log(f"  candidate {name:15s} explained {e:+.3f}  fit {rec['fit_explained']:+.3f}"
        f"{f' (x{best_a:g})' if best_a > 0 else ' (no change: not better on its fit episodes)'}  params {values}"
        f"{msg}  ({time.time() - tc:.0f} s)")
    return {"rec": rec, "res": res, "base": bases, "load_res": load_res,
            "load_base": load_bases if load_res is not None else None}


_WORK: Optional[_CandidateWork] = None  # a worker process's copy of the work (set by _init_worker)


def _init_worker(work: _CandidateWork) -> None:
    global _WORK
    torch.set_num_threads(1)
    _WORK = work


def _fit_in_worker(name: str) -> tuple[str, Optional[dict], list[str]]:
    lines: list[str] = []
    return name, fit_candidate(_WORK, name, lines.append), lines


def _map_candidates(w: _CandidateWork, names: list[str], log: Callable[[str], None]):
    """Yield (name, fit_candidate's result, its log lines) per candidate, in ``names`` order:
    one after another (lines logged live, none returned), or with ``cfg.jobs`` > 1 in that many
    fresh worker processes (spawned, not forked: no thread or lock of the parent, a ROS
    executor's say, is inherited), each sent the work once, with one torch thread; CPU models
    only (a CUDA model fits one candidate at a time). The fits are independent and seeded
    alike, so the results do not depend on the number of workers."""
    jobs = min(int(w.cfg.jobs), len(names))
    on_cpu = all(p.device.type == "cpu" for p in w.sim.parameters())
    if jobs > 1 and not on_cpu:
        log(f"  jobs={w.cfg.jobs} needs a CPU model: fitting one candidate at a time")
    if jobs <= 1 or not on_cpu:
        for name in names:
            yield name, fit_candidate(w, name, log), []
        return
    from concurrent.futures import ProcessPoolExecutor

    log(f"  fitting {len(names)} candidates in {jobs} worker processes (one torch thread each; each "
        "candidate's lines when it is done)")
    with ProcessPoolExecutor(max_workers=jobs, mp_context=mp.get_context("spawn"), initializer=_init_worker,
                             initargs=(w,)) as ex:
        for f in [ex.submit(_fit_in_worker, n) for n in names]:
            yield f.result()


def rank_candidates(sim: Simulator, fit_obs: Sequence[EpisodeObs], held_obs: Sequence[EpisodeObs],
                    base: Sequence[np.ndarray], scene: SceneContext, cfg: DiscrepancyConfig,
                    log: Callable[[str], None] = print, ref_obs: Sequence[EpisodeObs] = (),
                    ref_scene: Optional[SceneContext] = None, fit_res: Optional[Sequence[np.ndarray]] = None,
                    ref_res: Optional[Sequence[np.ndarray]] = None, base_load: Optional[Sequence[np.ndarray]] = None):
    """Fit every candidate alone; its explained fraction of the held-out 3D residual; bootstrap;
    decision. Returns (named, ranking, decision, fits, fitted models, bootstrap samples).

    ``base``: per held-out episode, per scored frame, the residual of the unchanged model.
    Without ``ref_obs``, a candidate starts at 0 and explained = 1 - residual(fitted) /
    ``base``. With ``ref_obs`` (episodes of the conditions the model was trained in) the
    candidate is first *calibrated* there (fitted from 0 on ``ref_obs``: the part of the
    term that fixes the model's own error on any data, e.g. a tighter grip for a model that
    under-lifts), then re-fitted from that on the measured fit episodes, and explained = 1 -
    residual(re-fitted) / min(residual(calibrated), residual(unchanged), residual(continued))
    on the held-out episodes, where "continued" is the calibration fitted on ``ref_obs`` for
    as many more steps as the re-fit takes on the measured ones: what the new data asks of the
    term beyond every model that assumes nothing new (the calibration, fitted on a few
    episodes, need not carry over; a calibration that had not converged would otherwise hand
    the re-fit's extra steps to the new data). Effect-free data asks
    for nothing more (explained ~ 0); an effect of the opposite sign to the model's own error
    (a slipping grip on a model that under-lifts) is still seen.

    ``fit_res`` / ``ref_res`` / ``base_load``: the unchanged model's per-frame residuals of ``fit_obs`` /
    ``ref_obs`` and |wrist load error| of ``held_obs`` when the caller has them already (else they are
    computed)."""
    ref_scene = ref_scene or scene
    if fit_res is None:
        fit_res = [residual_per_frame(sim, o, scene) for o in fit_obs]
    if ref_res is None:
        ref_res = [residual_per_frame(sim, o, ref_scene) for o in ref_obs]
    start = (objective_at_start(sim, ref_obs, ref_scene, cfg, float(sum(r.sum() for r in ref_res))) if ref_obs
             else objective_at_start(sim, fit_obs, scene, cfg, float(sum(r.sum() for r in fit_res))))
    den0 = max(sum(float(x.sum()) for x in base), 1e-12)
    with_load = bool(cfg.load_channel) and bool(held_obs) and all(o.load is not None for o in held_obs)
    if not with_load:
        base_load = None
    elif base_load is None:
        base_load = [scores_per_frame(sim, o, scene)[1] for o in held_obs]
    if cfg.load_channel and not with_load:
        log("  wrist load: not every held-out episode has /joint_states efforts; candidates are ranked on the "
            "3D residual alone")
    elif with_load:
        err = np.concatenate(base_load)
        meas = np.concatenate([o.load for o in held_obs])
        log(f"  wrist load: measured {np.mean(meas):.3f} N on average over the held-out scored frames, the unchanged "
            f"model's error {np.mean(err):.3f} N")
    work = _CandidateWork(sim, list(fit_obs), list(held_obs), list(base), scene, cfg, list(ref_obs), ref_scene,
                          start, den0, base_load)
    cand_res: dict[str, list[np.ndarray]] = {}
    cand_base: dict[str, list[list[np.ndarray]]] = {}  # per candidate: its baselines (the smallest sum counts)
    load_res: dict[str, list[np.ndarray]] = {}
    load_base: dict[str, list[list[np.ndarray]]] = {}
    fits: dict[str, dict] = {}
    models: dict[str, Simulator] = {}
    for name, out, lines in _map_candidates(work, list(cfg.candidates), log):
        for line in lines:
            log(line)
        if out is None:
            continue
        fits[name] = out["rec"]
        cand_res[name], cand_base[name] = out["res"], out["base"]
        if with_load:
            load_res[name], load_base[name] = out["load_res"], out["load_base"]
        models[name] = with_effect(sim, name, out["rec"]["parameters"], cfg)
    samples = bootstrap_explained(cand_base, cand_res, cfg.bootstrap, cfg.seed) if cand_res else {}
    # the same seed and frame counts: the same resamples as the 3D residual's (paired channels)
    lsamples = bootstrap_explained(load_base, load_res, cfg.bootstrap, cfg.seed) if with_load and load_res else None
    named, ranking, decision = decide({k: v["explained_fraction"] for k, v in fits.items()}, samples, cfg.alpha,
                                      cfg.min_explained,
                                      {k: v["load_explained"] for k, v in fits.items()} if lsamples else None, lsamples)
    decision["calibrated_on_reference"] = bool(ref_obs)
    log(f"  named effect: {named} ({json.dumps(_json_safe(decision))})")
    return named, ranking, decision, fits, models, samples


# --------------------------------------------------------------------------- main
def _resolve_run(checkpoint: Path) -> tuple[Path, Path]:
    ck = Path(checkpoint)
    if ck.is_dir():
        ck = ck / "checkpoint.pt"
    if not ck.is_file():
        raise FileNotFoundError(f"checkpoint not found: {ck}")
    return ck, ck.parent


def _json_safe(x):
    if isinstance(x, dict):
        return {str(k): _json_safe(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_json_safe(v) for v in x]
    if isinstance(x, (np.floating, float)):
        return None if not math.isfinite(float(x)) else float(x)
    if isinstance(x, np.integer):
        return int(x)
    return x


def run_discrepancy(checkpoint: Path, data: Path, out: Path, cfg: Optional[DiscrepancyConfig] = None,
                    scene_dir: Optional[Path] = None, log: Callable[[str], None] = print) -> dict:
    """The whole workflow (module docstring); returns the report dict (also DIR/report.json)."""
    from soma_ros.evaluation.baselines import SimulatorModel
    from soma_ros.discrepancy.report import write_report
    from soma_ros.evaluation.evaluate import EvalConfig, EvalContext, evaluate_models

    cfg = (cfg or DiscrepancyConfig()).validate()
    t0 = time.time()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    ck, run = _resolve_run(checkpoint)
    cfg_path = run / "train_config.yaml"
    if not cfg_path.is_file():
        raise FileNotFoundError(f"{run}: no train_config.yaml next to the checkpoint (a `soma train` run folder is needed)")
    scene_dir = Path(scene_dir) if scene_dir is not None else run / "scene"
    if not (scene_dir / "scene.json").is_file():
        raise FileNotFoundError(f"scene bundle not found: {scene_dir}")
    train_cfg = load_train_config(cfg_path)
    ref_data, is_training_data = reference_dataset(cfg, read_checkpoint(ck)["extra"])  # fail before any work
    ctx = EvalContext(data, train_cfg, scene_dir, cache_dir=out / "cache")
    sim = load_model(ck, cfg)
    torch.manual_seed(cfg.seed)
    scene = ctx.scene

    # ---- episodes
    mark_heldout(ctx, cfg)
    held = [r for r in ctx.refs if r.split == HELDOUT]
    fit = [r for r in ctx.refs if r.split != HELDOUT]
    if not held or not fit:
        raise ValueError(f"{data}: need both held-out ('{cfg.heldout_split}') and fit episodes "
                         f"(have {len(held)} held-out, {len(fit)} other)")
    if cfg.max_heldout_episodes:
        held = held[: cfg.max_heldout_episodes]
    if cfg.max_fit_episodes:
        fit = fit[: cfg.max_fit_episodes]
    obs: dict[str, EpisodeObs] = {}
    stage1: dict[str, dict] = {}
    L1 = sim.hierarchy.parents[0].cpu()
    n_clusters = int(sim.hierarchy.sizes[1])
    mcfg = EvalMetricsConfig(with_lpips=False)
    log(f"discrepancy: {len(fit)} fit + {len(held)} held-out episodes, candidates {', '.join(cfg.candidates)}")
    for ref in fit + held:
        ob, ep = episode_obs(ctx, ref, cfg)
        init, frames = ob.init, ob.frames
        obs[ref.name] = ob
        # -- step 1/2: resimulate, locate (per-frame, per-camera depth / image; 3D; per cluster)
        colors, opac = init.colors().float(), init.opacities.float()
        rec = {"frames": frames, "points": [], "depth_rmse": [], "psnr": [], "cluster_residual": [],
               "task": ref.task, "split": ref.split, "cameras": list(ep.camera_names), "worst": None, "load": []}
        worst = -1.0
        with torch.no_grad():
            for i, (t, st) in enumerate(_rollout(sim, ob, scene, frames)):
                means = st.means.float()
                r, idx, vec = point_residual(ob.points[i], means)
                rec["points"].append(float(r))
                if ob.load is not None:  # as scores_per_frame: the unchanged model's |load error|
                    rec["load"].append(abs(float(ob.load[i]) - predicted_load(sim, init.mass, st.means,
                                                                                float(ob.gripper[t]), scene)))
                cl = torch.full((n_clusters, 3), float("nan"))
                if len(idx):
                    c = L1[idx]
                    s = torch.zeros(n_clusters, 3).index_add_(0, c, vec.float())
                    k = torch.bincount(c, minlength=n_clusters).float()
                    has = k > 0
                    cl[has] = s[has] / k[has, None]
                rec["cluster_residual"].append(cl.numpy())
                cams = ep.cameras(t)
                rr = render(means, st.covs.float(), colors, opac, cams)
                table = table_depth(cams, scene.plane_normal.float(), float(scene.plane_offset))
                fs = score_frame(t, rr.rgb, rr.depth, rr.alpha, ep.rgb[t], ep.depth[t], ep.object_mask[t],
                                 ep.robot_mask[t], table, ep.camera_names, cfg=mcfg)
                rec["depth_rmse"].append([fs.per_camera[c]["rmse"] for c in ep.camera_names])
                rec["psnr"].append([fs.per_camera[c]["psnr"] for c in ep.camera_names])
                if float(r) > worst:
                    worst = float(r)
                    m = ep.object_mask[t] & ~ep.robot_mask[t] & (ep.depth[t] > 0)
                    err = torch.where(m | (rr.alpha > 0.5), (rr.depth - ep.depth[t]).abs(), torch.zeros_like(rr.depth))
                    rec["worst"] = {"frame": t, "depth_error": err.numpy(), "gt_rgb": ep.rgb[t].numpy(),
                                    "sim_rgb": rr.rgb.clamp(0, 1).numpy()}
        rec["cluster_residual"] = np.stack(rec["cluster_residual"])  # [F, K, 3]
        stage1[ref.name] = rec
        log(f"  resim {ref.name} ({ref.split}, {ref.task}): 3D residual {1000 * np.mean(rec['points']):.1f} mm, "
            f"depth RMSE {np.nanmean(rec['depth_rmse']):.4f} m")
    fit_obs = [obs[r.name] for r in fit]
    held_obs = [obs[r.name] for r in held]
    base = [np.asarray(stage1[o.name]["points"]) for o in held_obs]

    # ---- the own-error control: episodes of the conditions the model was trained in
    ref_obs: list[EpisodeObs] = []
    ref_scene = scene
    if ref_data is None:
        log("  no reference data (the model's training conditions): candidates are tested on the held-out "
            "explained fraction alone")
    else:
        rctx = EvalContext(ref_data, train_cfg, scene_dir)
        rrefs = rctx.refs
        if is_training_data:
            rrefs = [r for r in rrefs if r.split != "train"]
            if not rrefs:
                log(f"  reference: {ref_data} has no episodes outside its train split; the control is off")
        if cfg.reference_episodes and len(rrefs) > cfg.reference_episodes:
            pick = np.linspace(0, len(rrefs) - 1, cfg.reference_episodes).round().astype(int)
            rrefs = [rrefs[i] for i in pick]
        ref_obs = [episode_obs(rctx, r, cfg)[0] for r in rrefs]
        ref_scene = rctx.scene
        if ref_obs:
            log(f"  reference: {len(ref_obs)} episodes of {ref_data} (own-error control)")

    # ---- is there a disagreement beyond the model's own error at all? (measured vs reference episodes)
    ref_res = [residual_per_frame(sim, o, ref_scene) for o in ref_obs]
    measured_mean = {r.name: float(np.mean(stage1[r.name]["points"])) for r in fit + held}  # per episode, m
    ref_mean = [float(r.mean()) for r in ref_res]
    detection = detect_discrepancy(list(measured_mean.values()), ref_mean, cfg.bootstrap, cfg.alpha, cfg.seed,
                                   measured_tasks=[r.task for r in fit + held], reference_tasks=[o.task for o in ref_obs])
    if detection["assessed"]:
        log(f"  residual vs the reference episodes{' (same-task pairs)' if detection['stratified_by_task'] else ''}: "
            f"AUC {detection['auc']:.2f} (lower bound {detection['auc_low']:.2f}), median x{detection['median_ratio']:.2f}: "
            f"discrepancy {'detected' if detection['detected'] else 'not detected'}")

    per_episode, beyond = episode_residuals(
        {r.name: {"task": r.task, "split": r.split, "residual": measured_mean[r.name],
                  "depth_rmse": float(np.nanmean(stage1[r.name]["depth_rmse"]))} for r in fit + held},
        [(o.task, m) for o, m in zip(ref_obs, ref_mean)])
    if ref_obs:
        names = [k for k, v in per_episode.items() if v["beyond_reference"]]
        log(f"  {beyond['count']} of {len(per_episode)} episodes beyond the largest reference residual of their task "
            f"({beyond['expected_by_chance']:.1f} expected by chance, P(>= {beyond['count']}) = {beyond['p_value']:.3f})"
            + (f": {', '.join(names)}" if names else ""))

    # ---- step 3: candidate fits and held-out explained fraction
    fit_res = [np.asarray(stage1[o.name]["points"]) for o in fit_obs]
    held_load = ([np.asarray(stage1[o.name]["load"]) for o in held_obs]
                 if all(o.load is not None for o in held_obs) else None)
    named, ranking, decision, fits, models, samples = rank_candidates(sim, fit_obs, held_obs, base, scene, cfg, log,
                                                                      ref_obs, ref_scene, fit_res, ref_res, held_load)

    # ---- step 4: add, save, re-evaluate on the held-out episodes
    after = models[named] if named != "none" else sim
    model_dir = out / "model"
    model_dir.mkdir(parents=True, exist_ok=True)
    extra = dict(read_checkpoint(ck)["extra"])
    extra["discrepancy"] = {"source_checkpoint": str(ck), "measured": str(data), "named_effect": named,
                            "parameters": fits[named]["parameters"] if named != "none" else {}}
    save_checkpoint(model_dir / "checkpoint.pt", after, extra=_json_safe(extra))
    shutil.copy2(cfg_path, model_dir / "train_config.yaml")
    if (model_dir / "scene").exists():
        shutil.rmtree(model_dir / "scene")
    shutil.copytree(scene_dir, model_dir / "scene")
    ecfg = EvalConfig(metrics=mcfg, frame_stride=cfg.eval_frame_stride, max_episodes=cfg.max_heldout_episodes or None,
                      contact_sheets=cfg.contact_sheets, sheet_frames=4, progress=False)
    ev = evaluate_models({"before": SimulatorModel(sim), "after": SimulatorModel(after)}, ctx, HELDOUT,
                         {"before": out / "eval" / "before", "after": out / "eval" / "after"}, ecfg, log=log)
    res_after = [residual_per_frame(after, o, scene) for o in held_obs]
    gap = {}
    for k, res in (("gap_before", base), ("gap_after", res_after)):
        m = ev["before" if k == "gap_before" else "after"]["mean"]
        g = {metric: m.get(metric) for metric in ("rmse", "chamfer", "abs_rel", "psnr", "ssim")}
        g["points"] = float(np.mean(np.concatenate(res)))
        gap[k] = g
    report = {
        "named_effect": named,
        "ranking": ranking,
        "gap_before": gap["gap_before"],
        "gap_after": gap["gap_after"],
        "decision": decision,
        "discrepancy": detection,
        "episode_residuals": per_episode,
        "episodes_beyond_reference": beyond,
        "fits": {k: {kk: vv for kk, vv in v.items()} for k, v in fits.items()},
        "episodes": {"fit": [r.name for r in fit], "heldout": [r.name for r in held],
                     "reference": [o.name for o in ref_obs]},
        "reference_data": None if ref_data is None else str(ref_data),
        "checkpoint_in": str(ck),
        "checkpoint_out": str(model_dir / "checkpoint.pt"),
        "data": str(data),
        "config": dataclasses.asdict(cfg),
        "metric_notes": {
            "points": "workflow's 3D residual: mean distance observed object point -> nearest simulated splat (m)",
            "rmse": "depth RMSE (m), eval protocol (soma_ros.evaluation.evaluate), held-out episodes",
            "chamfer": "EVALUATION ONLY: vs /world/object_points by soma_ros.evaluation.evaluate; never used by the decision",
        },
        "seconds": round(time.time() - t0, 1),
    }
    report = _json_safe(report)
    (out / "report.json").write_text(json.dumps(report, indent=1))
    write_report(out, report, stage1, samples, n_clusters, sim)
    log(f"discrepancy: wrote {out / 'report.md'}, {out / 'report.json'} ({report['seconds']:.0f} s)")
    return report
