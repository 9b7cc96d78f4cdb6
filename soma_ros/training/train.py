"""`soma train`: fit the simulator offline from the bags of a dataset.

    soma train --data DATASET --config tiny --out RUN          # one process
    torchrun --nproc_per_node 2 -m soma_ros.cli train ...      # DDP (gloo on CPU, nccl on GPU)

RUN gets ``checkpoint.pt`` (the simulator, :func:`~soma_ros.core.checkpoint.save_checkpoint`;
with ``run.keep: best`` the weights with the lowest validation loss so far, the untrained ones
included, with ``best_points`` those with the lowest validation point distance, else the latest), ``checkpoint_last.pt`` (the latest weights), ``scene/`` (the scene bundle the nodes load, plus ``hierarchy.pt``), ``train_state.pt``
(optimiser and schedule, for resuming), ``log.csv``, ``loss.png``, ``val_tasks.csv`` and
``val_tasks.png`` (the validation figures per task, :func:`write_val_tasks`), ``train_config.yaml``.
With ``run.keep: best_score`` the kept weights are those with the lowest :func:`selection_score`
(image loss, scored-region depth and point distance per validation task, relative to the untrained
model). Validation episodes are stratified over the training split's tasks (:func:`split_validation`).

One iteration (per rank): pick a training episode, roll the simulator out from
that episode's initial state (G_0 aligned to its first frame, see
:func:`soma_ros.scene.scene_setup.align_splats`) under its recorded actions, render
every predicted state in every camera and compare with the recorded frame:

    L = mean_{frames, cameras} [lam masked-L2 + (1 - lam) D-SSIM](object pixels, robot pixels excluded)
        + w_mom L_mom / M^2 + w_depth masked-L1(depth) + w_net mean_steps |network output|^2

then Adam with the gradient norm clipped, in two parameter groups with their own learning rate and
warm-up (:func:`param_groups`: the network, the physical terms). The temporal schedule is the
paper's two-stage multi-resolution one: stage 1 steps ``stride`` frames at a
time (dt_sim = stride x dt) from frame 0 with a rollout that grows every
epoch; stage 2 runs at the frame rate on random windows whose start state
comes from a no-grad rollout from frame 0.

Resuming: ``train_state.pt`` (weights, optimiser, iteration, written
atomically with every checkpoint) is picked up when the same command runs
again in the same RUN; the iteration counter, the weights and the Adam
moments carry on, and the per-iteration randomness is a function of the
iteration, so a resumed run follows the same schedule.

Distribution: ``torch.distributed`` is initialised from the torchrun
environment (RANK, WORLD_SIZE, LOCAL_RANK, MASTER_ADDR/PORT); the loss module
is wrapped in :class:`~torch.nn.parallel.DistributedDataParallel`; each rank
rolls out its own episode per iteration; validation episodes are split over
the ranks and reduced; rank 0 writes every file.
"""

from __future__ import annotations

import csv
import dataclasses
import json
import math
import os
import tempfile
import time
from collections import OrderedDict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional, Sequence

import numpy as np
import torch
from torch import nn

from soma_ros.core.checkpoint import atomic_torch_save, load_train_state, save_checkpoint, save_train_state
from soma_ros.core.config import load_object_config
from soma_ros.core.hierarchy import Hierarchy
from soma_ros.core.metrics import masked_l2_dssim_loss
from soma_ros.core.render import render
from soma_ros.core.robot import RobotModel
from soma_ros.core.scene_bundle import SceneBundle
from soma_ros.core.simulator import SceneContext, SimState, Simulator
from soma_ros.core.splats import Splats

from soma_ros.training.config import TrainConfig, beyond_edge, search_past_edge
from soma_ros.data.dataset import EpisodeData, EpisodeRef, load_dataset, prepare_episode
from soma_ros.data.sources import usable_episodes, write_split
from soma_ros.core.scoring import complete_depth_maps, table_depth
from soma_ros.scene.files import load_scene, save_scene
from soma_ros.scene.scene_setup import align_splats, setup_scene

__all__ = [
    "DistInfo",
    "RolloutPlan",
    "EpisodeStore",
    "RolloutLoss",
    "stage_at",
    "lr_at",
    "param_groups",
    "make_optimizer",
    "split_validation",
    "selection_score",
    "write_val_tasks",
    "plan_rollout",
    "contact_frame",
    "rest_reach",
    "frame_terms",
    "total_loss",
    "observed_points",
    "rollout_full",
    "validate",
    "gripper_follow",
    "load_scene",
    "save_scene",
    "train",
    "TRAIN_STATE",
    "LOG_COLUMNS",
]

TRAIN_STATE = "train_state.pt"
TRAIN_STATE_FORMAT = "soma_ros.train_state/1"
LOG_COLUMNS = ["kind", "iteration", "epoch", "stage", "stride", "steps", "episode", "loss", "img",
               "depth", "points", "momentum", "grad_norm", "lr", "seconds", "follow", "network"]


# --------------------------------------------------------------------------- distribution
@dataclass
class DistInfo:
    """Process layout from the torchrun environment (single process without it)."""

    rank: int = 0
    world: int = 1
    local_rank: int = 0
    device: torch.device = field(default_factory=lambda: torch.device("cpu"))

    @property
    def is_main(self) -> bool:
        return self.rank == 0

    @property
    def distributed(self) -> bool:
        return self.world > 1

    def barrier(self) -> None:
        if self.distributed:
            torch.distributed.barrier()

    @staticmethod
    def from_env(device: str = "auto") -> "DistInfo":
        world = int(os.environ.get("WORLD_SIZE", "1"))
        rank = int(os.environ.get("RANK", "0"))
        local = int(os.environ.get("LOCAL_RANK", "0"))
        use_cuda = device == "cuda" or (device == "auto" and torch.cuda.is_available())
        if device == "cuda" and not torch.cuda.is_available():
            raise RuntimeError("config device 'cuda' but torch sees no CUDA device")
        dev = torch.device(f"cuda:{local}") if use_cuda else torch.device("cpu")
        if use_cuda:
            torch.cuda.set_device(dev)
        if world > 1 and not torch.distributed.is_initialized():
            torch.distributed.init_process_group(backend="nccl" if use_cuda else "gloo")
        return DistInfo(rank=rank, world=world, local_rank=local, device=dev)

    def all_reduce_sum(self, values: Sequence[float]) -> list[float]:
        if not self.distributed:
            return [float(v) for v in values]
        t = torch.tensor([float(v) for v in values], dtype=torch.float64,
                         device=self.device if self.device.type == "cuda" else "cpu")
        torch.distributed.all_reduce(t)
        return t.cpu().tolist()


# --------------------------------------------------------------------------- schedule
@dataclass
class StageInfo:
    stage: int  # 1 or 2
    epoch_in_stage: int
    stride: int  # frames per simulator step
    steps: int  # stage 1: rollout length in (strided) steps; stage 2: window length in frames


def stage_at(cfg: TrainConfig, epoch: int) -> StageInfo:
    s1, s2 = cfg.schedule.stage1, cfg.schedule.stage2
    if epoch < s1.epochs:
        return StageInfo(1, epoch, s1.stride, s1.length_start + s1.length_growth * epoch)
    return StageInfo(2, epoch - s1.epochs, 1, s2.window)


@dataclass
class RolloutPlan:
    """Which frames one training rollout steps through and supervises.

    The simulator steps ``stride`` frames at a time (dt_sim = stride x dt) from frame 0.
    ``prefix``: frames stepped without gradients first (stage 2's window start, and frames
    before the gripper comes within reach of the object: there the state is exactly the
    initial one -- the simulator's at-rest property -- so they carry no gradient);
    ``frames``: the frames stepped with gradients; ``supervised``: those of ``frames`` whose
    rendered loss counts (None = all). ``network_yaw`` (rad): the turn of the network's frame
    about gravity for this rollout (``schedule.yaw_augment``; 0 = the world frame).
    """

    episode: str
    stride: int
    prefix: list[int]
    frames: list[int]
    supervised: Optional[list[int]] = None
    network_yaw: float = 0.0

    @property
    def start(self) -> int:
        return self.prefix[-1] if self.prefix else 0

    @property
    def loss_frames(self) -> list[int]:
        return list(self.frames) if self.supervised is None else list(self.supervised)


def plan_rollout(info: StageInfo, episode: str, num_frames: int, rng: np.random.Generator, contact: int = 0,
                 sim_step: str = "stride") -> RolloutPlan:
    """The rollout of one iteration.

    Stage 1 (``sim_step="stride"``, the paper's): steps of k frames (dt_sim = k dt) at frames
    k, 2k, ...; ``sim_step="frame"``: steps of one frame, supervised every k-th frame. The
    rollout covers ``info.steps`` supervised frames from the first one at or after ``contact``
    (the first frame with a control point within reach of the object; earlier frames are
    provably at rest and go to the no-grad prefix). Stage 2: a window of ``info.steps``
    frames at the frame rate, starting at random (never wholly before ``contact``).
    """
    T = num_frames
    c = int(min(max(contact, 1), T - 1))
    if info.stage == 1:
        k = max(1, min(info.stride, T - 1))
        sup_all = list(range(k, T, k))
        first = next((i for i, f in enumerate(sup_all) if f >= c), len(sup_all) - 1)
        sup = sup_all[first: first + max(1, info.steps)]
        if sim_step == "stride":
            return RolloutPlan(episode, k, sup_all[:first], sup, None)
        start = min(c, sup[0])
        return RolloutPlan(episode, 1, list(range(1, start)), list(range(start, sup[-1] + 1)), sup)
    n = max(1, min(info.steps, T - 1))
    lo = max(0, min(c - n, T - 1 - n))
    s = int(rng.integers(lo, T - n))  # window = frames s+1 .. s+n
    return RolloutPlan(episode, 1, list(range(1, s + 1)), list(range(s + 1, s + n + 1)))


def contact_frame(ep: EpisodeData, init: Splats, reach: float) -> int:
    """First frame whose control points come within ``reach`` (m) of the initial splats
    (T if never): until then a simulator whose only non-reference effect is the robot
    force leaves the object exactly at rest."""
    x = init.means.detach().float()
    for t in range(ep.num_frames):
        d = torch.cdist(ep.control_points[t].float(), x).min()
        if float(d) < reach:
            return t
    return ep.num_frames


def rest_reach(sim: Simulator, margin: float = 0.01) -> Optional[float]:
    """Robot-effect radius + margin when the robot force is the model's only effect outside the
    at-rest reference, besides effects that vanish at rest (drag, table friction): then frames
    before contact are exactly at rest. Else None."""
    robot_keys = [k for k in sim.effects.keys() if sim.effects[k].robot_reach() is not None]
    others = [k for k in sim.effects.keys() if not sim.effects[k].in_reference and k not in robot_keys
              and not sim.effects[k].zero_at_rest]
    if others or not robot_keys:
        return None
    return max(sim.effects[k].robot_reach() for k in robot_keys) + margin


def _by_task(refs: Sequence[EpisodeRef]) -> "OrderedDict[str, list[EpisodeRef]]":
    out: "OrderedDict[str, list[EpisodeRef]]" = OrderedDict()
    for r in refs:
        out.setdefault(r.task or "", []).append(r)
    return out


def _round_robin(refs: Sequence[EpisodeRef]) -> list[EpisodeRef]:
    """``refs`` reordered one task at a time (first of every task, then second, ...), so that any
    prefix of the list is as balanced over the tasks as its length allows."""
    groups = list(_by_task(refs).values())
    return [g[i] for i in range(max((len(g) for g in groups), default=0)) for g in groups if i < len(g)]


def split_validation(train: Sequence[EpisodeRef], val: Optional[Sequence[EpisodeRef]], dc) -> tuple[list, list]:
    """(training episodes, validation episodes) from the training split ``train`` and, when the config
    names one, the validation split ``val`` (None: held out of ``train``, :class:`~soma_ros.training.config.DataConfig`).

    Stratified (``data.val_stratify``): the last ``val_holdout`` episodes of every task are held out,
    as long as the task keeps at least one training episode; the validation list is ordered
    round-robin over the tasks. Otherwise the last ``val_holdout`` episodes, at least one left to train."""
    train = list(train)
    if val is not None:
        return train, _round_robin(val) if dc.val_stratify else list(val)
    if not dc.val_stratify:
        k = min(dc.val_holdout, max(0, len(train) - 1))
        return train[: len(train) - k], train[len(train) - k:]
    held: set[str] = set()
    for eps in _by_task(train).values():
        k = min(dc.val_holdout, len(eps) - 1)
        held.update(r.name for r in eps[len(eps) - k:] if k > 0)
    return [r for r in train if r.name not in held], _round_robin([r for r in train if r.name in held])


def selection_score(per_task: dict[str, dict], reference: dict[str, dict], terms: Sequence[str]) -> float:
    """``run.keep: best_score``: mean over the tasks of ``reference`` of the mean over ``terms`` of
    value / the reference's value (the untrained model's validation: it scores exactly 1). A task or
    term whose value is not finite makes the score inf (never kept); a reference value of 0 counts as
    1e-12 (m or loss units: only a model as exact scores 1 on it)."""
    vals = []
    for task, ref in reference.items():
        cur = per_task.get(task)
        if cur is None:
            return math.inf
        for k in terms:
            v, r = float(cur[k]), float(ref[k])
            if not math.isfinite(v) or not math.isfinite(r):
                return math.inf
            vals.append(v / max(r, 1e-12))
    return float(np.mean(vals)) if vals else math.inf


MAX_SKIPPED_IN_A_ROW = 5


@dataclass
class DivergenceGuard:
    """What the training loop does about steps it cannot take (a non-finite loss or gradient).

    One such step is skipped and the weights are kept (:func:`clipped_step`). ``in_a_row`` of
    them mean the weights themselves have run away (a stiff rollout that blows up from here on,
    whatever the episode): the loop goes back to the kept weights (the best validation so far)
    with fresh Adam moments and the learning rate times ``lr_factor`` per rollback, at most
    ``max_rollbacks`` times; then, or with no validated weights to go back to, it stops with an
    error. ``skipped`` / ``rollbacks``: the iterations, kept across a resume (the count in a row too:
    :meth:`resume_at`)."""

    in_a_row: int = MAX_SKIPPED_IN_A_ROW
    max_rollbacks: int = 2
    lr_factor: float = 0.5
    skipped: list = field(default_factory=list)
    rollbacks: list = field(default_factory=list)
    run: int = 0  # skipped steps in a row now

    @property
    def lr_scale(self) -> float:
        return self.lr_factor ** len(self.rollbacks)

    def update(self, it: int, stepped: bool, can_roll_back: bool) -> str:
        """After iteration ``it``: "stepped", "skipped" or "rollback" (the caller restores the
        weights); raises RuntimeError when the run cannot go on."""
        if stepped:
            self.run = 0
            return "stepped"
        self.skipped.append(it)
        self.run += 1
        if self.run < self.in_a_row:
            return "skipped"
        last = self.skipped[-self.in_a_row:]
        if not can_roll_back:
            raise RuntimeError(f"iterations {last}: {self.in_a_row} non-finite losses or gradients in a row and no "
                               "validated weights to go back to; lower optim.lr or optim.grad_clip")
        if len(self.rollbacks) >= self.max_rollbacks:
            raise RuntimeError(f"iterations {last}: {self.in_a_row} non-finite losses or gradients in a row after "
                               f"{len(self.rollbacks)} rollback(s) (at iterations {self.rollbacks}); lower optim.lr "
                               "or optim.grad_clip")
        self.rollbacks.append(it)
        self.run = 0
        return "rollback"

    def resume_at(self, it: int) -> "DivergenceGuard":
        """A run resuming at iteration ``it`` carries on the count of skipped steps in a row: the
        saved skipped iterations that end at ``it - 1`` without a gap, after the last rollback
        (which restarted the count). Returns self."""
        done = set(self.skipped)
        last_rollback = self.rollbacks[-1] if self.rollbacks else -1
        k = it - 1
        while k in done and k > last_rollback:
            k -= 1
        self.run = it - 1 - k
        return self


def clipped_step(opt: torch.optim.Optimizer, params, clip: float) -> tuple[float, bool]:
    """Clip the gradients' total norm to ``clip`` and take the optimiser step; returns (the norm
    before clipping, whether the step was taken). A non-finite gradient (a backward that
    overflowed through a long, stiff rollout) is dropped and the weights are kept: clipping cannot
    repair it, and one Adam step with it would make every weight NaN."""
    gn = float(torch.nn.utils.clip_grad_norm_(list(params), clip))
    if not math.isfinite(gn):
        opt.zero_grad(set_to_none=True)
        return gn, False
    opt.step()
    return gn, True


PARAM_GROUPS = ("network", "physics")


def lr_at(cfg: TrainConfig, it: int, group: Optional[str] = None) -> float:
    """Learning rate at iteration ``it``: the cosine decay of ``optim.lr`` to ``lr * lr_final_factor``
    over the run; for a parameter group (``network`` / ``physics``) of its own peak rate, times
    its linear warm-up ``(it + 1) / warmup_iters`` during the first ``warmup_iters`` iterations."""
    o = cfg.optim
    total = max(1, cfg.schedule.total_iters)
    f = o.lr_final_factor + (1 - o.lr_final_factor) * 0.5 * (1 + math.cos(math.pi * min(it, total) / total))
    if group is None:
        return o.lr * f
    w = getattr(o, group).warmup_iters
    return o.group_lr(group) * f * (min(1.0, (it + 1) / w) if w > 0 else 1.0)


def param_groups(sim: Simulator) -> dict[str, list[nn.Parameter]]:
    """The simulator's trainable parameters by optimiser group: ``network`` = the graph network and
    the learned per-splat attributes it reads, ``physics`` = every effect's parameters. Raises if a
    parameter belongs to neither (a new module must be placed in one deliberately)."""
    groups: dict[str, list[nn.Parameter]] = {g: [] for g in PARAM_GROUPS}
    for name, prm in sim.named_parameters():
        if not prm.requires_grad:
            continue
        if name.startswith("gnn.") or name == "splat_attrs":
            groups["network"].append(prm)
        elif name.startswith("effects."):
            groups["physics"].append(prm)
        else:
            raise ValueError(f"param_groups: parameter {name!r} is neither the network's nor an effect's")
    return groups


def make_optimizer(sim: Simulator, cfg: TrainConfig) -> torch.optim.Adam:
    """Adam with one parameter group per :data:`PARAM_GROUPS` entry (in that order; an empty group is
    left out), each at its iteration-0 learning rate (:func:`lr_at`)."""
    o = cfg.optim
    groups = [{"params": ps, "lr": lr_at(cfg, 0, g), "name": g} for g, ps in param_groups(sim).items() if ps]
    return torch.optim.Adam(groups, lr=o.lr, betas=tuple(o.betas), weight_decay=o.weight_decay)


# --------------------------------------------------------------------------- data
class EpisodeStore:
    """Prepared episodes (LRU in memory) and their initial splats (cached on disk in ``cache_dir``)."""

    def __init__(self, refs: Sequence[EpisodeRef], robot: RobotModel, cfg: TrainConfig, bundle: SceneBundle,
                 hierarchy: Hierarchy, cache_dir: Optional[Path]) -> None:
        self.refs = {r.name: r for r in refs}
        self.robot = robot
        self.cfg = cfg
        self.bundle = bundle
        self.hierarchy = hierarchy
        self.cache_dir = cache_dir
        #: True: every episode must have the scene's cameras (training); False: each bag's own (evaluation)
        self.rig_cameras = True
        self.base_to_sim = bundle.base_to_sim_sim3()
        self._eps: "OrderedDict[str, EpisodeData]" = OrderedDict()
        self._init: dict[str, Splats] = {}
        self._contact: dict[str, int] = {}

    def contact(self, name: str, reach: Optional[float]) -> int:
        """:func:`contact_frame` of the episode (0 when ``reach`` is None: no at-rest shortcut)."""
        if reach is None:
            return 0
        if name not in self._contact:
            self._contact[name] = contact_frame(self.episode(name), self.initial_splats(name), reach)
        return self._contact[name]

    def episode(self, name: str) -> EpisodeData:
        if name in self._eps:
            self._eps.move_to_end(name)
            return self._eps[name]
        ref = self.refs[name]
        data = self.cfg.data
        if data.cameras is None and self.bundle.cameras and self.rig_cameras:  # a bag missing one is an error
            data = dataclasses.replace(data, cameras=[c.name for c in self.bundle.cameras])
        ep = prepare_episode(ref.bag, self.robot, data, base_to_sim=self.base_to_sim, name=name,
                             mask_cache=None if self.cache_dir is None else self.cache_dir / "masks")
        self._eps[name] = ep
        while len(self._eps) > self.cfg.data.cache_episodes:
            self._eps.popitem(last=False)
        return ep

    def is_source(self, name: str) -> bool:
        """Whether episode ``name`` is the one the scene's G_0 was reconstructed from: the same name and,
        where the bundle records it, the same bag (another dataset's ``rope_000`` is a different rope
        and needs G_0 aligned to its own frame 0, like any other episode)."""
        extra = self.bundle.extra
        if name != extra.get("source_episode"):
            return False
        src = extra.get("source_bag")
        return src is None or Path(src).resolve() == Path(self.refs[name].bag).resolve()

    def initial_splats(self, name: str) -> Splats:
        """G_0 aligned to the episode's frame-0 object points (G_0 itself for its source episode)."""
        if name in self._init:
            return self._init[name]
        if self.is_source(name):
            sp = self.bundle.splats
        else:
            path = None if self.cache_dir is None else self.cache_dir / f"{name}.init.pt"
            sp = None
            if path is not None and path.is_file():
                d = torch.load(path, weights_only=True)
                if d.get("n") == len(self.bundle.splats):
                    g = self.bundle.splats
                    sp = Splats(d["means"], d["quats"], g.scales, g.opacities, g.sh_dc, g.sh_rest, g.mass, g.attrs)
            if sp is None:
                ep = self.episode(name)
                tgt, _ = ep.object_points([0], erode_px=self.cfg.scene.erode_px)
                sp, _ = align_splats(self.bundle.splats, tgt, self.bundle.table_normal, self.cfg.scene,
                                     clusters=self.hierarchy.parents[0].cpu())
                if path is not None:
                    _atomic_torch_save({"n": len(sp), "means": sp.means, "quats": sp.quats}, path)
        self._init[name] = sp
        return sp


# --------------------------------------------------------------------------- loss
def _scene_ctx(bundle: SceneBundle, dt: float, device, dtype) -> SceneContext:
    base = bundle.scene_context()
    return SceneContext(base.gravity, base.plane_normal, base.plane_offset, dt).to(device=device, dtype=dtype)


LOSS_TERMS = ("img", "depth", "points", "momentum", "network")


def frame_terms(sim_state: SimState, colors: torch.Tensor, opacities: torch.Tensor, ep: EpisodeData, t: int,
                cfg: TrainConfig, device, points: Optional[torch.Tensor] = None,
                plane: Optional[tuple[torch.Tensor, float]] = None,
                scored_depth: bool = False) -> dict[str, torch.Tensor]:
    """Loss terms (scalars) of one predicted state against frame t in all cameras:

    * ``img``: the paper's lam masked-L2 + (1 - lam) D-SSIM on object pixels (robot pixels are
      not in the mask), per camera then averaged (``loss.camera_reduce``);
    * ``depth`` (if weighted): mean |rendered - recorded depth| (m) on object pixels
      (``loss.depth_region: object``) or on the evaluation's scored region with both maps
      completed by the table depth (``scored``; needs ``plane`` = (table normal [3], offset));
    * ``points`` (if weighted): mean distance (m) from each observed object point of the frame
      (``points`` [M, 3], the frame's fused masked depth) to the nearest predicted splat centre:
      only what the cameras see is constrained, so occluded parts stay free;
    * ``depth_scored`` (with ``scored_depth``, whatever the weights): the ``depth`` term on the
      scored region (validation's geometric figure; needs ``plane``).
    """
    lc = cfg.loss
    z = sim_state.means.new_zeros(())
    terms = {"depth": z, "points": z}
    cams = ep.cameras(t, dtype=sim_state.means.dtype, device=device)
    out = render(sim_state.means, sim_state.covs, colors, opacities, cams)
    gt = ep.rgb[t].to(device=device, dtype=out.rgb.dtype)
    mask = ep.loss_mask[t].to(device)
    if lc.camera_reduce == "camera":  # the paper's sum over images: every camera weighs the same
        terms["img"] = torch.stack([
            masked_l2_dssim_loss(out.rgb[c:c + 1], gt[c:c + 1], mask[c:c + 1], lam=lc.lam, window_size=lc.dssim_window,
                                 dssim_reduce=lc.dssim_reduce) for c in range(len(cams))]).mean()
    else:
        terms["img"] = masked_l2_dssim_loss(out.rgb, gt, mask, lam=lc.lam, window_size=lc.dssim_window,
                                            dssim_reduce=lc.dssim_reduce)

    def depth_term(region: str) -> torch.Tensor:
        gd = ep.depth[t].to(device=device, dtype=out.depth.dtype)
        if region == "scored":
            if plane is None:
                raise ValueError("frame_terms: the depth on the scored region needs the table plane")
            table = table_depth(cams, plane[0], float(plane[1])).to(device=device)
            pd, gdc, reg = complete_depth_maps(out.depth, out.alpha, gd, ep.object_mask[t].to(device),
                                               ep.robot_mask[t].to(device), table)
            m = reg.to(pd.dtype)
            err = m * (pd - gdc).abs()
        else:
            m = (mask & (gd > 0)).to(out.depth.dtype)
            err = m * (out.depth - gd).abs()
        if lc.camera_reduce == "camera":
            return (err.sum(dim=(1, 2)) / m.sum(dim=(1, 2)).clamp_min(1.0)).mean()
        return err.sum() / m.sum().clamp_min(1.0)

    if lc.depth_weight > 0:
        terms["depth"] = depth_term(lc.depth_region)
    if scored_depth:
        terms["depth_scored"] = terms["depth"] if lc.depth_weight > 0 and lc.depth_region == "scored" \
            else depth_term("scored")
    if lc.points_weight > 0:
        if points is None:
            points = observed_points(ep, t, lc.points_max)
        if len(points):
            d = torch.cdist(points.to(device=device, dtype=sim_state.means.dtype), sim_state.means)
            terms["points"] = d.min(dim=1).values.mean()
    return terms


def _plane(bundle: SceneBundle) -> tuple[torch.Tensor, float]:
    """(table normal [3], offset) of the scene bundle's table plane."""
    sc = bundle.scene_context()
    return torch.as_tensor(sc.plane_normal).reshape(3), float(sc.plane_offset)


def observed_points(ep: EpisodeData, t: int, max_points: int) -> torch.Tensor:
    """Frame t's fused object points [M, 3] (M <= max_points, an evenly strided subset)."""
    p, _ = ep.object_points([t])
    if len(p) > max_points:
        p = p[torch.linspace(0, len(p) - 1, max_points).round().long()]
    return p


def total_loss(terms: dict[str, torch.Tensor], cfg: TrainConfig) -> torch.Tensor:
    """The weighted sum of the loss terms (``network``: the network's contribution, 0 if absent)."""
    lc = cfg.loss
    loss = (terms["img"] + lc.depth_weight * terms["depth"] + lc.points_weight * terms["points"]
            + lc.momentum_weight * terms["momentum"])
    if lc.network_weight > 0 and "network" in terms:
        loss = loss + lc.network_weight * terms["network"]
    return loss


class RolloutLoss(nn.Module):
    """The training objective of one rollout; the module DDP wraps (its forward is the whole
    rollout, so DDP sees every parameter use)."""

    def __init__(self, sim: Simulator, cfg: TrainConfig, bundle: SceneBundle) -> None:
        super().__init__()
        self.sim = sim
        self.cfg = cfg
        self.bundle = bundle
        self.plane = _plane(bundle)

    def forward(self, ep: EpisodeData, init: Splats, plan: RolloutPlan) -> tuple[torch.Tensor, dict]:
        sim, cfg = self.sim, self.cfg
        dev, dt_ = sim.device, sim.dtype
        sp = init.to(device=dev, dtype=dt_)
        colors, opac = sp.colors(), sp.opacities
        total_mass = float(sp.mass.sum())
        ctx = _scene_ctx(self.bundle, ep.dt * plan.stride, dev, dt_)
        if plan.prefix:
            with torch.no_grad():
                state = sim.init_state(sp, ctx, network_yaw=plan.network_yaw)
                for t in plan.prefix:
                    state = sim.step(state, ep.action(t, dt_, dev))
            state = sim.refresh_reference(state.detach())
        else:
            state = sim.init_state(sp, ctx, network_yaw=plan.network_yaw)
        sums = {k: state.means.new_zeros(()) for k in LOSS_TERMS}
        net_sq = state.means.new_zeros(())  # the network's contribution, summed over every step with gradients
        sup = set(plan.loss_frames)
        for t in plan.frames:
            state = sim.step(state, ep.action(t, dt_, dev))
            if cfg.loss.network_weight > 0 and state.network_sq is not None:
                net_sq = net_sq + state.network_sq
            if t not in sup:
                continue
            for k, v in frame_terms(state, colors, opac, ep, t, cfg, dev, plane=self.plane).items():
                sums[k] = sums[k] + v
            if cfg.loss.momentum_weight > 0:
                sums["momentum"] = sums["momentum"] + sim.momentum_loss(state) / (total_mass * total_mass)
        n = max(1, len(sup))
        terms = {k: v / n for k, v in sums.items()}
        terms["network"] = net_sq / max(1, len(plan.frames))
        loss = total_loss(terms, cfg)
        if not loss.requires_grad:  # e.g. the gripper never reaches the object: no gradient, keep ranks in step
            loss = loss + sum(p.sum() for p in sim.parameters() if p.requires_grad) * 0.0
        return loss, {k: float(v.detach()) for k, v in terms.items()}


# --------------------------------------------------------------------------- validation
@torch.no_grad()
def rollout_full(sim: Simulator, ep: EpisodeData, init: Splats, bundle: SceneBundle,
                 frames: Optional[Sequence[int]] = None) -> list[SimState]:
    """Open-loop rollout at the frame rate from frame 0; states of frames 1..T-1 (or up to max(frames))."""
    dev, dt_ = sim.device, sim.dtype
    sp = init.to(device=dev, dtype=dt_)
    state = sim.init_state(sp, _scene_ctx(bundle, ep.dt, dev, dt_))
    last = ep.num_frames - 1 if not frames else max(frames)
    out = [state]
    for t in range(1, last + 1):
        state = sim.step(state, ep.action(t, dt_, dev))
        out.append(state)
    return out


@torch.no_grad()
def gripper_follow(states: Sequence[SimState], ep: EpisodeData, up: torch.Tensor, radius: float = 0.03,
                   close_below: float = 0.5) -> Optional[dict]:
    """How far the splats near the gripper rise with it during a grasp, from the predicted states
    (state t = frame t). Splats within ``radius`` of the control points' centroid at the frame
    where the gripper first closes (c < ``close_below``) are followed to the last frame; returns
    {"grasp_frame", "gripper_rise", "splat_rise", "ratio" = splat_rise / gripper_rise,
    "n_splats"} (None if the gripper never closes or does not rise)."""
    closed = torch.nonzero(ep.gripper < close_below).flatten()
    if closed.numel() == 0:
        return None
    tc = int(closed[0])
    last = len(states) - 1
    if last <= tc:
        return None
    up = up.double() / up.double().norm()
    grip_c = ep.control_points[tc].double().mean(0)
    grip_e = ep.control_points[last].double().mean(0)
    rise_g = float((grip_e - grip_c) @ up)
    x_c = states[tc].means.detach().double().cpu()
    near = (x_c - grip_c).norm(dim=-1) < radius
    if rise_g <= 1e-3 or int(near.sum()) == 0:
        return None
    x_e = states[last].means.detach().double().cpu()
    rise_s = float(((x_e[near] - x_c[near]) @ up).mean())
    return {"grasp_frame": tc, "gripper_rise": rise_g, "splat_rise": rise_s, "ratio": rise_s / rise_g,
            "n_splats": int(near.sum())}


VAL_FIGURES = ("val_loss", "img", "depth", "points")


@torch.no_grad()
def validate(sim: Simulator, store: EpisodeStore, names: Sequence[str], cfg: TrainConfig,
             dist: Optional[DistInfo] = None) -> dict:
    """Validation: full-rate open-loop rollout of each episode from its initial state (the way
    the live node runs the model), scored on every ``val_frame_stride``-th frame.

    ``val_loss``: the training objective's data terms (:func:`total_loss` without the
    momentum regulariser) with the config's weights, mean over frames and episodes;
    ``img``: the paper's image loss L_img alone; ``depth``: mean |depth error| (m) on the
    evaluation's scored region (both maps completed with the table plane), whatever its weight;
    ``points``: mean distance (m) from the observed object points to the nearest predicted splat
    (whatever its weight); ``follow``: mean :func:`gripper_follow` ratio. ``per_task``: the same
    figures per task of the episodes (``""`` = no task recorded), each the mean over that task's
    frames. Episodes are split over the ranks and reduced."""
    dist = dist or DistInfo()
    was = sim.training
    sim.eval()
    tasks = list(OrderedDict.fromkeys((store.refs[n].task or "") for n in names))
    # per task: sums of the VAL_FIGURES, frame count, follow sum, follow count, episodes
    acc = np.zeros((len(tasks), len(VAL_FIGURES) + 4))
    plane = _plane(store.bundle)
    for i, name in enumerate(names):
        if i % dist.world != dist.rank:
            continue
        row = acc[tasks.index(store.refs[name].task or "")]
        ep = store.episode(name)
        states = rollout_full(sim, ep, store.initial_splats(name), store.bundle)
        init = store.initial_splats(name).to(device=sim.device, dtype=sim.dtype)
        frames = list(range(cfg.run.val_frame_stride, ep.num_frames, cfg.run.val_frame_stride))
        for t in frames:
            obs = observed_points(ep, t, cfg.loss.points_max)
            terms = frame_terms(states[t], init.colors(), init.opacities, ep, t, cfg, sim.device, points=obs,
                                plane=plane, scored_depth=True)
            terms["momentum"] = terms["img"].new_zeros(())
            row[:4] += [float(total_loss(terms, cfg)), float(terms["img"]), float(terms["depth_scored"]),
                        _point_distance(states[t].means, obs)]
            row[4] += 1
        f = gripper_follow(states, ep, torch.as_tensor(store.bundle.table_normal))
        if f is not None:
            row[5] += f["ratio"]
            row[6] += 1
        row[7] += 1
    acc = np.asarray(dist.all_reduce_sum(acc.ravel().tolist())).reshape(acc.shape)
    sim.train(was)

    def figures(r: np.ndarray) -> dict:  # Python floats: they go into checkpoints loaded with weights_only
        n = max(float(r[4]), 1.0)
        return {**{k: float(r[j]) / n for j, k in enumerate(VAL_FIGURES)},
                "follow": float(r[5] / r[6]) if r[6] else float("nan"), "frames": int(r[4]), "episodes": int(r[7])}

    out = figures(acc.sum(axis=0))
    out["per_task"] = {task: figures(acc[j]) for j, task in enumerate(tasks)}
    return out


_IDENTIFY_ATTR = {"stretch": "log_stretch", "bend": "log_bend", "grip": "log_grip", "tilt": "log_tilt",
                  "damping": "log_damping", "friction": "friction"}


@torch.no_grad()
def identify_prior(sim: Simulator, store: EpisodeStore, names: Sequence[str], cfg: TrainConfig, criterion: str,
                   dist: Optional[DistInfo] = None, say=print) -> dict:
    """System identification before training (:class:`~soma_ros.training.config.IdentifyConfig`): score the
    untrained model with the physics prior's coefficient at each grid value on ``names`` (training
    episodes) like a validation; while the best lies on the grid's edge, up to ``extend`` values
    beyond it (:func:`~soma_ros.training.config.search_past_edge`, each kept only while it scores lower); set the best
    (``criterion``: ``val_loss`` or ``points``; ties keep the earlier value) and return
    ``{coefficient, criterion, episodes, chosen, rows}`` (rows beyond the grid: ``extended`` true)."""
    from soma_ros.core.effects.physics import PhysicsPrior

    terms = [sim.effects[k] for k in sim.effects.keys() if isinstance(sim.effects[k], PhysicsPrior)]
    if len(terms) != 1:
        raise ValueError(f"identify: needs exactly one effect 'physics' in the model, found {len(terms)}")
    ic = cfg.identify
    param = getattr(terms[0], _IDENTIFY_ATTR[ic.coefficient], None)
    if param is None:
        raise ValueError(f"identify: the physics effect has no coefficient {ic.coefficient!r} "
                         "(tilt: set grip_tilt_compliance > 0 on it)")
    log = ic.coefficient != "friction"
    rows: list[dict] = []
    scores: list[float] = []  # the criterion of each row (inf where not finite)

    def score(v: float, extended: bool) -> float:
        param.fill_(math.log(v) if log else v)
        r = validate(sim, store, names, cfg, dist)
        rows.append({"value": v, **{k: float(r[k]) for k in ("val_loss", "img", "points", "follow")},
                     **({"extended": True} if extended else {})})
        say(f"identify {ic.coefficient} = {v:g}{' (beyond the grid)' if extended else ''}: "
            f"val_loss {r['val_loss']:.5f}, points {1e3 * r['points']:.2f} mm")
        scores.append(r[criterion] if math.isfinite(r[criterion]) else math.inf)
        return scores[-1]

    for v in ic.values:
        score(v, False)
    i = int(np.argmin(scores))
    _, _, tried = search_past_edge(ic.values, ic.values[i], scores[i], lambda v: score(v, True), ic.extend, log)
    best = rows[int(np.argmin(scores))]
    param.fill_(math.log(best["value"]) if log else best["value"])
    on_edge = beyond_edge(tried, best["value"], log) is not None
    say(f"identify: {ic.coefficient} = {best['value']:g} (lowest {criterion} on {len(names)} training episodes"
        + ("; on the edge of the values tried" if on_edge else "") + ")")
    return {"coefficient": ic.coefficient, "criterion": criterion, "episodes": list(names), "chosen": best["value"],
            "rows": rows}


def _point_distance(means: torch.Tensor, points: torch.Tensor) -> float:
    if len(points) == 0:
        return 0.0
    return float(torch.cdist(points.to(means), means).min(dim=1).values.mean())


# --------------------------------------------------------------------------- files
def _atomic_torch_save(obj, path: Path) -> None:
    atomic_torch_save(obj, path)


def _atomic_write_text(path: Path, text: str) -> None:
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(text)
    os.replace(tmp, path)


class RunLog:
    """``log.csv`` (append; rows past a resumed iteration are dropped) and ``loss.png``."""

    def __init__(self, path: Path, resume_iteration: Optional[int]) -> None:
        self.path = path
        rows = []
        if resume_iteration is not None and path.is_file():
            with open(path, newline="") as f:
                for r in csv.DictReader(f):
                    try:
                        if int(r["iteration"]) <= resume_iteration:
                            rows.append(r)
                    except (KeyError, ValueError):
                        continue
        self.rows = rows
        with open(path, "w", newline="") as f:
            w = csv.DictWriter(f, LOG_COLUMNS)
            w.writeheader()
            for r in rows:
                w.writerow({k: r.get(k, "") for k in LOG_COLUMNS})

    def add(self, **row) -> None:
        r = {k: row.get(k, "") for k in LOG_COLUMNS}
        for k, v in r.items():
            if isinstance(v, float):
                r[k] = f"{v:.6g}"
        self.rows.append(r)
        with open(self.path, "a", newline="") as f:
            csv.DictWriter(f, LOG_COLUMNS).writerow(r)

    def plot(self, out: Path, title: str = "") -> None:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        tr = [(int(r["iteration"]), float(r["loss"])) for r in self.rows if r["kind"] == "train" and r["loss"]]
        va = [(int(r["iteration"]), float(r["loss"])) for r in self.rows if r["kind"] == "val" and r["loss"]]
        fig, ax = plt.subplots(figsize=(7, 4), dpi=100)
        if tr:
            x, y = np.array(tr).T
            ax.plot(x, y, lw=0.6, alpha=0.35, color="C0", label="train (per iteration)")
            k = max(1, len(y) // 30)
            if k > 1:
                ys = np.convolve(y, np.ones(k) / k, mode="valid")
                ax.plot(x[k - 1:], ys, color="C0", lw=1.5, label=f"train ({k}-iteration mean)")
        if va:
            x, y = np.array(va).T
            ax.plot(x, y, "o-", color="C3", label="validation (full-rate rollout)")
        stages = [(int(r["iteration"]), r["stage"]) for r in self.rows if r["kind"] == "train" and r["stage"]]
        for (i0, s0), (i1, s1) in zip(stages, stages[1:]):
            if s1 != s0:
                ax.axvline(i0, color="0.5", ls="--", lw=0.8)
                ax.text(i0, 1.0, f" stage {s1}", transform=ax.get_xaxis_transform(), va="top", fontsize=7,
                        color="0.4")
        ax.set_xlabel("iteration (stage 1: the rollout grows every epoch, so its loss rises)")
        ax.set_ylabel("loss")
        ax.set_yscale("log")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
        ax.set_title(title, fontsize=9)
        fig.tight_layout()
        tmp = out.with_name(f".{out.stem}.tmp.png")
        fig.savefig(tmp)
        plt.close(fig)
        os.replace(tmp, out)


VAL_TASKS_COLUMNS = ["iteration", "task", *VAL_FIGURES, "follow", "score_terms_ratio"]


def write_val_tasks(out_dir: Path, history: Sequence[dict], terms: Sequence[str], kept: Optional[int],
                    title: str = "") -> None:
    """``val_tasks.csv`` (one row per validation and task, the figures of :func:`validate`, and the
    task's mean ratio of ``terms`` to its first validation = its share of the selection score) and
    ``val_tasks.png`` (one panel per figure, a line per task; ``kept``: the kept iteration, marked)."""
    rows = [h for h in history if h.get("per_task")]
    if not rows:
        return
    first = rows[0]["per_task"]
    table = []
    for h in rows:
        for task, f in h["per_task"].items():
            ref = first.get(task)
            ratio = float(np.mean([f[k] / max(ref[k], 1e-12) for k in terms])) if ref else float("nan")
            table.append({"iteration": h["iteration"], "task": task or "-", **{k: f[k] for k in VAL_FIGURES},
                          "follow": f.get("follow", float("nan")), "score_terms_ratio": ratio})
    tmp = out_dir / ".val_tasks.csv.tmp"
    with open(tmp, "w", newline="") as fh:
        w = csv.DictWriter(fh, VAL_TASKS_COLUMNS)
        w.writeheader()
        for r in table:
            w.writerow({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in r.items()})
    os.replace(tmp, out_dir / "val_tasks.csv")

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = [("score_terms_ratio", f"mean of {'+'.join(terms)} / untrained"), ("img", "image loss L_img"),
              ("depth", "depth |error| (m, scored region)"), ("points", "point distance (m)")]
    fig, axes = plt.subplots(1, len(panels), figsize=(4 * len(panels), 3.4), dpi=100)
    for ax, (key, label) in zip(axes, panels):
        for j, task in enumerate(dict.fromkeys(r["task"] for r in table)):
            pts = [(r["iteration"], r[key]) for r in table if r["task"] == task]
            x, y = np.array(pts).T
            ax.plot(x, y, "o-", ms=3, color=f"C{j}", label=task)
        if kept is not None:
            ax.axvline(kept, color="0.4", ls="--", lw=0.8)
        ax.set_title(label, fontsize=9)
        ax.set_xlabel("iteration")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8, title="task" + (" (-- kept)" if kept is not None else ""), title_fontsize=8)
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    tmp = out_dir / ".val_tasks.tmp.png"
    fig.savefig(tmp)
    plt.close(fig)
    os.replace(tmp, out_dir / "val_tasks.png")


# --------------------------------------------------------------------------- the run
def _config_fingerprint(cfg: TrainConfig) -> dict:
    """The parts of the config a resumed run must share with the original."""
    return {"model": cfg.model_config().to_dict(), "object": cfg.object, "robot": cfg.robot,
            "data": dataclasses.asdict(cfg.data), "scene": dataclasses.asdict(cfg.scene)}


def _weights_checksum(sim: Simulator) -> float:
    return float(sum(p.detach().double().abs().sum().cpu() for p in sim.parameters()))


def train(cfg: TrainConfig, data_dir: Path, out_dir: Path, scene_dir: Optional[Path] = None,
          max_iterations: Optional[int] = None, log=print, max_seconds: Optional[float] = None) -> dict:
    """Run (or resume) a training run; returns a summary dict (rank 0's view).

    ``max_iterations``: stop after this global iteration (a partial run that can be resumed;
    for tests and time-boxed jobs). ``max_seconds``: stop once the training loop (iterations and
    their validations, from the first iteration on; not the scene set-up) has run this long, then
    validate the weights reached (unless just validated) and checkpoint them: a time-boxed run whose
    kept checkpoint has seen its last weights; resumable like a ``max_iterations`` stop. Under DDP
    the replicas stop at the same iteration, on rank 0's clock read at that iteration's forward pass
    (it travels in the collective that every iteration makes anyway).
    ``log``: where one-line messages go (rank 0 only).
    """
    if max_seconds is not None and not max_seconds > 0:
        raise ValueError(f"max_seconds must be > 0 (got {max_seconds})")
    torch.set_num_threads(int(os.environ.get("OMP_NUM_THREADS", "1") or 1))
    dist = DistInfo.from_env(cfg.device)
    say = log if dist.is_main else (lambda *a, **k: None)
    if isinstance(data_dir, (list, tuple)):  # several bags (soma_ros.data.sources): one is its path
        data_dir = Path(data_dir[0]) if len(data_dir) == 1 else [Path(p) for p in data_dir]
    else:
        data_dir = Path(data_dir)
    out_dir = Path(out_dir)
    try:
        return _train(cfg, data_dir, out_dir, scene_dir, max_iterations, dist, say, max_seconds)
    finally:
        if dist.distributed and torch.distributed.is_initialized():
            torch.distributed.destroy_process_group()


def _set_up_scene(cfg, scene_dir, scene_out, train_refs, val_refs, robot, obj, model_cfg, data_dir, say) -> None:
    """RUN/scene from ``scene_dir`` (a bundle) or from the first frame of the source episode."""
    if scene_dir is not None:
        bundle, hier = load_scene(scene_dir)
        save_scene(scene_out, bundle, hier)
        say(f"scene: copied from {scene_dir} ({len(bundle.splats)} splats)")
    else:
        src_name = cfg.scene.source_episode or train_refs[0].name
        src = {r.name: r for r in train_refs + val_refs}.get(src_name)
        if src is None:
            raise ValueError(f"scene.source_episode '{src_name}' is not an episode of {data_dir}")
        t0 = time.time()
        ep0 = prepare_episode(src.bag, robot, cfg.data, name=src.name, mask_cache=scene_out.parent / "cache" / "masks")
        setup = setup_scene(ep0, cfg.scene, obj.name, cfg.robot, obj.total_mass, model_cfg.hierarchy.thresholds,
                            model_cfg.hierarchy.seed_fraction, progress=False)
        save_scene(scene_out, setup.bundle, setup.hierarchy, setup.info)
        say(f"scene: {len(setup.bundle.splats)} splats from {src.name} ({setup.info['fused_points']} fused points), "
            f"hierarchy {setup.hierarchy.sizes}, table normal {np.round(setup.bundle.table_normal, 3).tolist()}, "
            f"{time.time() - t0:.1f} s")


def _train(cfg, data_dir, out_dir, scene_dir, max_iterations, dist: DistInfo, say,
           max_seconds: Optional[float] = None) -> dict:
    t_start = time.time()
    if dist.is_main:
        out_dir.mkdir(parents=True, exist_ok=True)
    dist.barrier()
    dc = cfg.data
    robot = RobotModel.from_config(cfg.robot, dtype=torch.float64)
    split_args = dict(test_fraction=dc.split_test_fraction, seed=dc.split_seed)
    train_refs = usable_episodes(load_dataset(data_dir, dc.train_split, dc.tasks, **split_args), robot, dc, say)
    if dist.is_main:
        write_split(out_dir, data_dir, load_dataset(data_dir, **split_args), **split_args)
    val_refs = (usable_episodes(load_dataset(data_dir, dc.val_split, dc.tasks, **split_args), robot, dc, say)
                if dc.val_split is not None else None)
    train_refs, val_refs = split_validation(train_refs, val_refs, dc)
    if dc.val_stratify and val_refs:
        missing = sorted({r.task or "" for r in train_refs} - {r.task or "" for r in val_refs[: cfg.run.val_episodes]})
        if missing:
            say(f"validation sees no episode of task(s) {', '.join(missing)} (a single training episode each, "
                "or run.val_episodes too small)")
    if dc.max_train_episodes:
        train_refs = train_refs[: dc.max_train_episodes]
    if dc.max_val_episodes:
        val_refs = val_refs[: dc.max_val_episodes]
    if not train_refs:
        raise ValueError(f"{data_dir}: no training episodes (split '{dc.train_split}', tasks {dc.tasks})")
    obj = load_object_config(cfg.object)
    model_cfg = cfg.model_config()

    # ---- resume?
    state_path = out_dir / TRAIN_STATE
    resume = load_train_state(state_path, TRAIN_STATE_FORMAT, say)  # checksum verified; falls back to the previous
    if resume is not None:
        if resume["fingerprint"] != json.loads(json.dumps(_config_fingerprint(cfg))):
            raise ValueError(f"{out_dir} holds a run with a different model/data/scene config; "
                             "use another --out or the same config to resume")

    # ---- scene (rank 0 sets it up, the others load it)
    scene_out = out_dir / "scene"
    failure: Optional[BaseException] = None
    try:
        if dist.is_main and not (scene_out / "scene.json").is_file():
            _set_up_scene(cfg, scene_dir, scene_out, train_refs, val_refs, robot, obj, model_cfg, data_dir, say)
    except Exception as exc:  # tell the other ranks instead of leaving them at the barrier
        failure = exc
    if dist.all_reduce_sum([1.0 if failure is not None else 0.0])[0] > 0:
        if failure is not None:
            raise failure
        raise RuntimeError("rank 0 failed to set up the scene (see its error)")
    bundle, hier = load_scene(scene_out)
    if dist.is_main:
        _atomic_write_text(out_dir / "train_config.yaml", cfg.to_yaml())

    # ---- model, optimiser
    torch.manual_seed(cfg.seed)
    sim = Simulator(model_cfg)
    sim.bind_hierarchy(hier)
    sim.to(dist.device)
    sim.train()
    if resume is not None:
        sim.load_state_dict(resume["model"])
    module = RolloutLoss(sim, cfg, bundle)
    if dist.distributed:
        ddp = nn.parallel.DistributedDataParallel(
            module, device_ids=[dist.device.index] if dist.device.type == "cuda" else None,
            find_unused_parameters=True)
    else:
        ddp = module
    opt = make_optimizer(sim, cfg)
    start_it = 0
    resumed_from = []
    if resume is not None:
        opt.load_state_dict(resume["optimizer"])
        start_it = int(resume["iteration"])
        resumed_from = list(resume.get("resumed_from", [])) + [start_it]
        say(f"resuming from iteration {start_it} (weights checksum {_weights_checksum(sim):.6f})")

    store = EpisodeStore(train_refs + val_refs, robot, cfg, bundle, hier, out_dir / "cache")
    reach = rest_reach(sim)
    train_names = [r.name for r in train_refs]
    val_names = [r.name for r in val_refs][: cfg.run.val_episodes]
    ipe = cfg.schedule.iters_per_epoch
    total = cfg.schedule.total_iters
    stop = total if max_iterations is None else min(total, int(max_iterations))
    runlog = RunLog(out_dir / "log.csv", start_it if resume is not None else None) if dist.is_main else None
    best_val = float(resume["best_val"]) if resume is not None and resume.get("best_val") is not None else None
    # the kept weights' criterion: the validation loss (run.keep: best) or point distance (best_points)
    # (best_score: the selection score against the untrained model's per-task validation, score_ref)
    crit = {"best_points": "points", "best_score": "score"}.get(cfg.run.keep, "val_loss")
    score_ref = resume.get("score_ref") if resume is not None else None
    best_score = resume.get("best_score", best_val) if resume is not None else None
    first_val = resume.get("first_val") if resume is not None else None
    last_val = resume.get("last_val") if resume is not None else None
    val_history: list = list(resume.get("val_history", [])) if resume is not None else []
    # the kept weights (run.keep: best / best_points): a CPU copy of the state dict with the lowest criterion
    best_iteration = resume.get("best_iteration") if resume is not None else None
    best_state = resume.get("best_model") if resume is not None else None
    if resume is not None and resume.get("best_criterion", "val_loss") != crit and best_state is not None:
        say(f"run.keep changed to {cfg.run.keep}: the kept weights are chosen among the validations from here on")
        best_val = best_score = best_iteration = best_state = None

    def checkpoint(it: int, epoch: int, final: bool = False) -> None:
        if not dist.is_main:
            return
        payload = {"format": TRAIN_STATE_FORMAT, "iteration": it, "epoch": epoch,
                   "model": {k: v.detach().cpu() for k, v in sim.state_dict().items()},
                   "optimizer": _to_cpu(opt.state_dict()), "fingerprint": json.loads(json.dumps(_config_fingerprint(cfg))),
                   "best_val": best_val, "best_score": best_score, "best_criterion": crit, "score_ref": score_ref,
                   "first_val": first_val, "last_val": last_val, "resumed_from": resumed_from,
                   "val_history": val_history, "best_iteration": best_iteration, "best_model": best_state,
                   "identified": identified, "skipped_iterations": guard.skipped, "rollbacks": guard.rollbacks,
                   "weights_checksum": _weights_checksum(sim)}
        save_train_state(payload, state_path)
        info = stage_at(cfg, min(epoch, cfg.schedule.epochs - 1))
        extra = {"iteration": it, "epoch": epoch, "stage": info.stage, "total_iterations": total,
                 "complete": bool(final and it >= total), "train_config": cfg.name, "dataset": str(data_dir) if isinstance(data_dir, Path) else ";".join(map(str, data_dir)),
                 "object": cfg.object, "robot": cfg.robot, "scene": "scene", "dt": float(bundle.dt),
                 "val_loss": last_val, "val_loss_untrained": first_val, "resumed_from": resumed_from,
                 "val_history": val_history,
                 "world_size": dist.world, "weights_checksum": _weights_checksum(sim),
                 "run_iteration": it, "kept": "last", "train_episodes": train_names, "val_episodes": val_names}
        save_checkpoint(out_dir / "checkpoint_last.pt", sim, extra=extra)
        if cfg.run.keep != "last" and best_state is not None:
            # checkpoint.pt: the weights of the best validation so far (not the latest ones)
            last_sd = {k: v.detach().clone() for k, v in sim.state_dict().items()}
            sim.load_state_dict(best_state)
            best_extra = dict(extra, iteration=best_iteration, epoch=best_iteration // ipe, kept=cfg.run.keep,
                              stage=stage_at(cfg, min(best_iteration // ipe, cfg.schedule.epochs - 1)).stage,
                              val_loss=best_val, weights_checksum=_weights_checksum(sim))
            save_checkpoint(out_dir / "checkpoint.pt", sim, extra=best_extra)
            sim.load_state_dict(last_sd)
        else:
            save_checkpoint(out_dir / "checkpoint.pt", sim, extra=extra)

    def run_validation(it: int, epoch: int) -> None:
        nonlocal best_val, best_score, first_val, last_val, best_iteration, best_state, score_ref
        if not val_names:
            return
        t0 = time.time()
        v = validate(sim, store, val_names, cfg, dist)
        last_val = v["val_loss"]
        if score_ref is None:  # the untrained model's per-task figures: the selection score's reference
            score_ref = {t: {k: float(f[k]) for k in VAL_FIGURES} for t, f in v["per_task"].items()}
        v["score"] = selection_score(v["per_task"], score_ref, cfg.run.score_terms)
        val_history.append({"iteration": it, **{k: float(v[k]) for k in ("val_loss", "img", "depth", "points",
                                                                          "follow", "score")},
                            "per_task": {t: {k: float(f[k]) for k in (*VAL_FIGURES, "follow")}
                                         for t, f in v["per_task"].items()}})
        if first_val is None:
            first_val = v["val_loss"]
        score = float(v[crit]) if math.isfinite(float(v[crit])) else math.inf  # no observed points: never better
        if best_score is None or score < best_score:  # ties keep the earlier weights
            best_score, best_val, best_iteration = score, v["val_loss"], it
            best_state = {k: t.detach().cpu().clone() for k, t in sim.state_dict().items()}
        if runlog is not None:
            runlog.add(kind="val", iteration=it, epoch=epoch, loss=v["val_loss"], img=v["img"],
                       points=v["points"], seconds=time.time() - t0, follow=v["follow"])
            runlog.plot(out_dir / "loss.png", f"{cfg.name}: {len(train_names)} train / {len(val_names)} val episodes")
            write_val_tasks(out_dir, val_history, cfg.run.score_terms, best_iteration,
                            f"{cfg.name}: validation per task ({len(val_names)} episodes)")

    identified = resume.get("identified") if resume is not None else None
    # iterations whose loss or gradient was not finite (no step taken), kept across a resume
    guard = DivergenceGuard(MAX_SKIPPED_IN_A_ROW, cfg.optim.max_rollbacks, cfg.optim.rollback_lr_factor,
                            list(resume.get("skipped_iterations", [])) if resume is not None else [],
                            list(resume.get("rollbacks", [])) if resume is not None else []).resume_at(start_it)
    if start_it == 0 and first_val is None and cfg.identify.values:
        k = min(cfg.identify.episodes, len(train_names))
        picks = [train_names[int(i)] for i in np.unique(np.linspace(0, len(train_names) - 1, k).round().astype(int))]
        identified = identify_prior(sim, store, picks, cfg, "val_loss" if crit == "score" else crit, dist, say)
        if dist.is_main:
            _atomic_write_text(out_dir / "identify.json", json.dumps(identified, indent=1))
    if start_it == 0 and first_val is None:
        run_validation(0, 0)
        if first_val is not None:
            say(f"validation loss of the untrained model: {first_val:.5f}")
        else:
            say("no validation episodes: checkpoint.pt holds the latest weights")
        checkpoint(0, 0)

    bar = None
    if dist.is_main and cfg.run.progress:
        from tqdm import tqdm

        bar = tqdm(total=stop, initial=start_it, desc="soma train", unit="it", dynamic_ncols=True)
    it = start_it
    used_episodes: list[str] = []
    t_loop = time.time()
    timed_out = False
    while it < stop:
        epoch = it // ipe
        info = stage_at(cfg, epoch)
        rng = np.random.default_rng([cfg.seed, it, dist.rank])
        perm = np.random.default_rng([cfg.seed, epoch, 7]).permutation(len(train_names))
        name = train_names[int(perm[((it % ipe) * dist.world + dist.rank) % len(train_names)])]
        used_episodes.append(name)
        ep = store.episode(name)
        init = store.initial_splats(name)
        plan = plan_rollout(info, name, ep.num_frames, rng, store.contact(name, reach), cfg.schedule.stage1.sim_step)
        if cfg.schedule.yaw_augment:  # drawn after the plan: without it the plans are those of earlier runs
            plan.network_yaw = float(rng.uniform(-math.pi, math.pi))
        for g in opt.param_groups:
            g["lr"] = lr_at(cfg, it, g["name"]) * guard.lr_scale
        lr = opt.param_groups[0]["lr"]  # the log's lr: the network's (the first group)
        t0 = time.time()
        loss, parts = ddp(ep, init, plan)
        finite_loss = bool(torch.isfinite(loss.detach()))
        if dist.distributed:
            # one collective per iteration, so every replica decides alike: skip if any replica's loss is
            # not finite, and (max_seconds) stop at the same iteration, on rank 0's clock at this forward pass
            bad, loop_s = dist.all_reduce_sum([0.0 if finite_loss else 1.0,
                                               time.time() - t_loop if dist.is_main else 0.0])
            finite_loss = bad == 0.0
        opt.zero_grad(set_to_none=True)
        if finite_loss:
            loss.backward()  # (DDP's gradient all-reduce: every replica takes this branch or none)
            gn, stepped = clipped_step(opt, sim.parameters(), cfg.optim.grad_clip)
        else:
            gn, stepped = float("nan"), False
        what = guard.update(it, stepped, best_state is not None)
        if what == "skipped":
            say(f"iteration {it}: non-finite {'gradient' if finite_loss else 'loss'} on episode {name} "
                f"(loss {float(loss.detach()):.4f}): step skipped, weights kept")
        elif what == "rollback":
            sim.load_state_dict(best_state)
            opt.state.clear()
            say(f"iteration {it}: {guard.in_a_row} non-finite steps in a row: back to the weights of iteration "
                f"{best_iteration} (the best validation), fresh Adam moments, learning rate x{guard.lr_scale:g} "
                f"from here on (rollback {len(guard.rollbacks)} of at most {guard.max_rollbacks})")
        it += 1
        dtime = time.time() - t0
        if runlog is not None:
            runlog.add(kind="train", iteration=it, epoch=epoch, stage=info.stage, stride=plan.stride,
                       steps=len(plan.frames), episode=name, loss=float(loss.detach()), grad_norm=gn, lr=lr,
                       seconds=dtime, **parts)
        if bar is not None:
            bar.update(1)
            bar.set_postfix(loss=f"{float(loss.detach()):.4f}", stage=info.stage, steps=len(plan.frames),
                            val=f"{last_val:.4f}" if last_val is not None else "-")
        end_of_epoch = it % ipe == 0
        validated = end_of_epoch and ((it // ipe) % cfg.run.val_every_epochs == 0 or it >= total)
        if validated:
            run_validation(it, it // ipe)
        if max_seconds is not None and it < stop:
            # one process: the clock now; under DDP: rank 0's at the forward pass (shared above)
            elapsed = loop_s if dist.distributed else time.time() - t_loop
            if elapsed >= max_seconds:
                timed_out = True
                if not validated:
                    run_validation(it, it // ipe)
        if end_of_epoch or it % cfg.run.checkpoint_every == 0 or it >= stop or timed_out:
            checkpoint(it, it // ipe, final=it >= total)
        if timed_out:
            say(f"stopped at iteration {it} of {total}: the training time limit ({max_seconds:g} s) is reached")
            break
    if bar is not None:
        bar.close()
    if runlog is not None:
        runlog.plot(out_dir / "loss.png", f"{cfg.name}: {len(train_names)} train / {len(val_names)} val episodes")
    summary = {"out": str(out_dir), "iterations": it, "total_iterations": total, "complete": it >= total,
               "timed_out": timed_out, "loop_seconds": round(time.time() - t_loop, 1),
               "world_size": dist.world, "val_loss_untrained": first_val, "val_loss": last_val,
               "val_history": val_history,
               "best_val_loss": best_val, "best_iteration": best_iteration, "kept": cfg.run.keep, "kept_score": best_score, "resumed_from": resumed_from, "seconds": round(time.time() - t_start, 1),
               "train_episodes": train_names, "val_episodes": val_names, "identified": identified,
               "skipped_iterations": guard.skipped, "rollbacks": guard.rollbacks}
    if dist.distributed:  # what each replica ends with: identical weights, its own episodes
        (out_dir / "dist").mkdir(exist_ok=True)
        _atomic_write_text(out_dir / "dist" / f"rank_{dist.rank}.json", json.dumps(
            {"rank": dist.rank, "world_size": dist.world, "weights_checksum": _weights_checksum(sim),
             "episodes": used_episodes}, indent=1))
        dist.barrier()
    if dist.is_main:
        _atomic_write_text(out_dir / "summary.json", json.dumps(summary, indent=1))
    if cfg.run.keep != "last" and best_iteration is not None and first_val is not None:
        say(f"kept iteration {best_iteration} in checkpoint.pt (validation loss {best_val:.5f}; untrained "
            f"{first_val:.5f}; last {last_val:.5f}" + (f"; selection score {best_score:.4f}, untrained 1"
                                                      if crit == "score" else "") + ")")
        if best_iteration == 0 and it > 0:
            say("training did not improve on the untrained model's validation: checkpoint.pt holds the untrained "
                "weights, checkpoint_last.pt the last ones")
    return summary


def _to_cpu(obj):
    if isinstance(obj, torch.Tensor):
        return obj.detach().cpu()
    if isinstance(obj, dict):
        return {k: _to_cpu(v) for k, v in obj.items()}
    if isinstance(obj, list):
        return [_to_cpu(v) for v in obj]
    return obj
