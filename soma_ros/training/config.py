"""Training configuration: dataclasses loaded strictly from YAML (``config/train/*.yaml``).

One :class:`TrainConfig` per run, with a section per concern:

=============  ==========================================================================
section        what it configures
=============  ==========================================================================
(top level)    model config (+ ``model_overrides`` merged into it), object config, robot
               config, seed, device
data           bag ingestion: cameras, topic names, synchronisation, training resolution,
               which manifest splits train and validate
scene          scene set-up: depth fusion, splat count, photometric refinement, table
               plane, per-episode alignment of G_0
loss           masked L2 + D-SSIM (lambda), momentum regulariser, optional depth term
schedule       the two-stage multi-resolution temporal schedule
optim          Adam, gradient clipping
run            checkpoint / validation / logging cadence
=============  ==========================================================================

Loading is strict (unknown keys and wrong types raise a one-line
:class:`~soma_ros.core.config.ConfigError` naming the key path), using the
core's generic :func:`~soma_ros.core.config.from_dict`.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping, Optional, Union

import yaml

from soma_ros.core.config import ConfigError, drop_retired_keys, from_dict, merge_config, read_config, to_dict

from soma_ros.data.config import DataConfig, TopicNames
from soma_ros.scene.config import SceneConfig
from soma_ros.paths import resolve_config

__all__ = [
    "ConfigError",
    "TopicNames",
    "DataConfig",
    "SceneConfig",
    "LossConfig",
    "Stage1Config",
    "Stage2Config",
    "ScheduleConfig",
    "ParamGroupConfig",
    "OptimConfig",
    "RunConfig",
    "TrainConfig",
    "load_train_config",
]


@dataclass
class LossConfig:
    """L = mean over supervised frames and cameras of [lam * masked L2 + (1 - lam) * D-SSIM]
    on object pixels (robot-occluded pixels excluded) + ``momentum_weight`` * L_mom
    + ``depth_weight`` * masked L1 depth (metres; 0 = the paper's image-only loss) on the
    pixels ``depth_region`` names ("object" = measured object pixels only; "scored" = the
    evaluation's rule, :func:`soma_ros.core.scoring.complete_depth_maps`, both maps completed
    with the table-plane depth, scored on object pixels or where the prediction renders
    (alpha > 0.5), robot pixels excluded -- so splats rendered where the camera sees the
    table cost too)
    + ``points_weight`` * mean distance observed object point -> nearest splat (m)
    (see :func:`soma_ros.training.train.frame_terms`)
    + ``network_weight`` * the network's mean squared contribution over the rollout's steps
    (:attr:`~soma_ros.core.simulator.SimState.network_sq`: |output - at-rest output|^2 per node,
    the residual acceleration in units of ``dynamics.accel_scale``): a pull towards the physical
    terms alone, so that the network departs from them only where the data's gradient outweighs it.

    ``camera_reduce``: "camera" = each camera's image loss on its own object pixels,
    then the mean over cameras (the paper sums L_img over images; a camera where the
    object is small weighs as much as the wrist camera where it fills the view);
    "pixel" = one pooled loss over all cameras' object pixels.

    L_mom is the simulator's :meth:`~soma_ros.core.simulator.Simulator.momentum_loss`
    divided by the squared total mass (so it is in m^2: a mean squared
    inconsistency of cluster centres), averaged over the supervised states.
    """

    lam: float = 0.9
    dssim_window: int = 5
    dssim_reduce: str = "image"
    camera_reduce: str = "camera"
    momentum_weight: float = 1.0
    depth_weight: float = 0.0
    depth_region: str = "object"  # the depth term's pixels: "object" or "scored" (above)
    points_weight: float = 0.0
    points_max: int = 1000
    network_weight: float = 0.0  # weight of the pull towards the physical terms alone (above)

    def validate(self, where: str = "loss") -> None:
        if not 0.0 <= self.lam <= 1.0:
            raise ConfigError(f"{where}.lam: must lie in [0, 1], got {self.lam}")
        if self.points_max < 1:
            raise ConfigError(f"{where}.points_max: must be >= 1, got {self.points_max}")
        if self.dssim_window < 1 or self.dssim_window % 2 == 0:
            raise ConfigError(f"{where}.dssim_window: must be an odd number >= 1, got {self.dssim_window}")
        if self.dssim_reduce not in ("image", "mask"):
            raise ConfigError(f"{where}.dssim_reduce: one of image, mask; got {self.dssim_reduce!r}")
        if self.depth_region not in ("object", "scored"):
            raise ConfigError(f"{where}.depth_region: one of object, scored; got {self.depth_region!r}")
        if self.camera_reduce not in ("camera", "pixel"):
            raise ConfigError(f"{where}.camera_reduce: one of camera, pixel; got {self.camera_reduce!r}")
        if min(self.momentum_weight, self.depth_weight, self.points_weight, self.network_weight) < 0:
            raise ConfigError(f"{where}: momentum_weight, depth_weight, points_weight and network_weight must be >= 0")


@dataclass
class Stage1Config:
    """Stage 1: temporal stride k from frame 0.

    ``sim_step: stride`` (the paper's): the simulator steps k frames at a time
    (dt_sim = k dt) and every step is supervised; ``frame``: it steps every frame
    (dt_sim = dt, the rate it will run at) and every k-th frame is supervised.
    The rollout covers ``length_start`` supervised frames in the first stage-1
    epoch and ``length_growth`` more every epoch (paper: +3), counted from the
    first frame where the gripper can touch the object (before it the object is
    exactly at rest and those steps run without gradients), capped by the episode.
    """

    epochs: int = 10
    stride: int = 10
    length_start: int = 3
    length_growth: int = 3
    sim_step: str = "stride"

    def validate(self, where: str = "schedule.stage1") -> None:
        if self.epochs < 0 or self.stride < 1 or self.length_start < 1 or self.length_growth < 0:
            raise ConfigError(f"{where}: epochs >= 0, stride >= 1, length_start >= 1, length_growth >= 0 required")
        if self.sim_step not in ("stride", "frame"):
            raise ConfigError(f"{where}.sim_step: one of stride, frame; got {self.sim_step!r}")


@dataclass
class Stage2Config:
    """Stage 2: full frame rate on windows of ``window`` frames (paper code: 13) at a
    random start; the state at the window start comes from a no-grad rollout."""

    epochs: int = 5
    window: int = 13

    def validate(self, where: str = "schedule.stage2") -> None:
        if self.epochs < 0 or self.window < 1:
            raise ConfigError(f"{where}: epochs >= 0 and window >= 1 required")


@dataclass
class ScheduleConfig:
    """Epochs of ``iters_per_epoch`` iterations (one episode rollout per iteration and rank).

    ``yaw_augment``: every training rollout runs the network in a frame turned about gravity by
    an angle drawn uniformly from [-pi, pi) (:meth:`~soma_ros.core.simulator.Simulator.init_state`
    ``network_yaw``). Table-top physics does not change under that turn; a network that reads
    world-frame vectors otherwise learns, from a few episodes, responses tied to the directions
    those episodes happened to have. The physical terms, validation, evaluation and the live node
    are not turned."""

    iters_per_epoch: int = 100
    stage1: Stage1Config = field(default_factory=Stage1Config)
    stage2: Stage2Config = field(default_factory=Stage2Config)
    yaw_augment: bool = False

    def validate(self, where: str = "schedule") -> None:
        if self.iters_per_epoch < 1:
            raise ConfigError(f"{where}.iters_per_epoch: must be >= 1, got {self.iters_per_epoch}")
        if not isinstance(self.yaw_augment, bool):
            raise ConfigError(f"{where}.yaw_augment: true or false, got {self.yaw_augment!r}")
        self.stage1.validate(f"{where}.stage1")
        self.stage2.validate(f"{where}.stage2")
        if self.stage1.epochs + self.stage2.epochs < 1:
            raise ConfigError(f"{where}: stage1.epochs + stage2.epochs must be >= 1")

    @property
    def epochs(self) -> int:
        return self.stage1.epochs + self.stage2.epochs

    @property
    def total_iters(self) -> int:
        return self.epochs * self.iters_per_epoch


@dataclass
class ParamGroupConfig:
    """One optimiser parameter group: ``lr`` (None = ``optim.lr``) reached after a linear warm-up
    of ``warmup_iters`` iterations from ``lr / warmup_iters`` (0 = none), then the run's cosine
    decay (``optim.lr_final_factor``), the same for every group."""

    lr: Optional[float] = None
    warmup_iters: int = 0

    def validate(self, where: str) -> None:
        if self.lr is not None and not (self.lr > 0 and math.isfinite(self.lr)):
            raise ConfigError(f"{where}.lr: must be > 0 (or null: optim.lr), got {self.lr}")
        if isinstance(self.warmup_iters, bool) or not isinstance(self.warmup_iters, int) or self.warmup_iters < 0:
            raise ConfigError(f"{where}.warmup_iters: an integer >= 0, got {self.warmup_iters!r}")


@dataclass
class OptimConfig:
    """Adam (paper: lr 4e-4, gradient clipping 1.0). ``lr_final_factor``: cosine decay of
    the learning rate to lr * factor over the run (1 = constant).

    Two parameter groups, each with its own learning rate and warm-up (:class:`ParamGroupConfig`):
    ``network`` = the graph network and the learned per-splat attributes it reads; ``physics`` =
    the effects' parameters (the robot coupling, the support, the physics prior, wind). Adam
    normalises every weight's step, so a network whose gradients are tiny next to the physical
    terms' still moves at the full learning rate: its own, lower one with a warm-up keeps the
    first steps from undoing what the physical terms give. One clip of the total gradient norm
    (``grad_clip``) over both groups."""

    lr: float = 4e-4
    network: ParamGroupConfig = field(default_factory=ParamGroupConfig)
    physics: ParamGroupConfig = field(default_factory=ParamGroupConfig)
    betas: list[float] = field(default_factory=lambda: [0.9, 0.999])
    weight_decay: float = 0.0
    grad_clip: float = 1.0
    lr_final_factor: float = 1.0
    # after MAX_SKIPPED_IN_A_ROW non-finite losses or gradients in a row: back to the kept (best validated)
    # weights with fresh Adam moments and the learning rate times rollback_lr_factor, at most this often
    max_rollbacks: int = 2
    rollback_lr_factor: float = 0.5

    def validate(self, where: str = "optim") -> None:
        if not (self.lr > 0 and math.isfinite(self.lr)):
            raise ConfigError(f"{where}.lr: must be > 0, got {self.lr}")
        if len(self.betas) != 2 or not all(0 <= b < 1 for b in self.betas):
            raise ConfigError(f"{where}.betas: two values in [0, 1), got {self.betas}")
        if self.weight_decay < 0 or not self.grad_clip > 0 or not 0 < self.lr_final_factor <= 1:
            raise ConfigError(f"{where}: weight_decay >= 0, grad_clip > 0, lr_final_factor in (0, 1] required")
        if not isinstance(self.max_rollbacks, int) or self.max_rollbacks < 0:
            raise ConfigError(f"{where}.max_rollbacks: an integer >= 0, got {self.max_rollbacks!r}")
        if not 0 < self.rollback_lr_factor < 1:
            raise ConfigError(f"{where}.rollback_lr_factor: must lie in (0, 1), got {self.rollback_lr_factor}")
        self.network.validate(f"{where}.network")
        self.physics.validate(f"{where}.physics")

    def group_lr(self, group: str) -> float:
        """The peak learning rate of parameter group ``group`` (``network`` or ``physics``)."""
        g = getattr(self, group)
        return self.lr if g.lr is None else g.lr


#: run.keep: the kept weights' criterion (validation), or the latest weights
KEEP = ("best", "best_points", "best_score", "last")
#: run.score_terms: validation figures the selection score (run.keep: best_score) can combine
SCORE_TERMS = ("val_loss", "img", "depth", "points")


@dataclass
class RunConfig:
    """Cadence: checkpoint every ``checkpoint_every`` iterations (and at each epoch end),
    validate every ``val_every_epochs`` epochs on at most ``val_episodes`` episodes,
    rendering every ``val_frame_stride``-th frame of a full-rate open-loop rollout.

    ``keep``: which weights the run's ``checkpoint.pt`` holds: ``best`` = those with the
    lowest validation loss so far (the untrained model's included), ``best_points`` = those
    with the lowest validation point distance (observed object points, back-projected from the
    recorded depth, to the nearest splat: the geometry, whatever the loss weights; the image
    loss alone can prefer an object that no longer follows the gripper), ``best_score`` = those
    with the lowest selection score: for every task of the validation episodes, each of
    ``score_terms`` (``img``: the image loss L_img; ``depth``: mean |depth error| (m) on the
    evaluation's scored region, both maps completed with the table plane; ``points``: the point
    distance; ``val_loss``) divided by the untrained model's value on that task, averaged over the
    terms, then over the tasks -- so the untrained model scores exactly 1, every task weighs the
    same and an image gain cannot hide a geometric loss; ``last`` = the latest.
    The latest weights are always in ``checkpoint_last.pt`` and ``train_state.pt`` (resume).
    Selecting on validation is model selection: the validation episodes must not be the
    held-out test episodes (see ``data.val_split``)."""

    checkpoint_every: int = 50
    val_every_epochs: int = 1
    val_episodes: int = 4
    val_frame_stride: int = 2
    keep: str = "best"
    score_terms: list[str] = field(default_factory=lambda: ["img", "depth", "points"])
    progress: bool = True

    def validate(self, where: str = "run") -> None:
        if self.checkpoint_every < 1 or self.val_every_epochs < 1 or self.val_episodes < 1 or self.val_frame_stride < 1:
            raise ConfigError(f"{where}: checkpoint_every, val_every_epochs, val_episodes, val_frame_stride must be >= 1")
        if self.keep not in KEEP:
            raise ConfigError(f"{where}.keep: one of {', '.join(KEEP)}; got {self.keep!r}")
        bad = [t for t in self.score_terms if t not in SCORE_TERMS]
        if bad or not self.score_terms or len(set(self.score_terms)) != len(self.score_terms):
            raise ConfigError(f"{where}.score_terms: distinct names among {', '.join(SCORE_TERMS)}; "
                              f"got {self.score_terms!r}")


IDENTIFY_COEFFICIENTS = ("stretch", "bend", "grip", "tilt", "damping", "friction")


def beyond_edge(values, edge: float, logarithmic: bool) -> Optional[float]:
    """The next value to try beyond ``edge`` when it is the first or last of ``values`` (None
    otherwise, or for fewer than two different values): that end's spacing continued, the ratio of
    its two outermost values (``logarithmic``: compliances, damping, line-search scales) or their
    difference (friction; clipped at 0, None once there)."""
    vs = sorted({float(v) for v in values})
    if len(vs) < 2 or edge not in (vs[0], vs[-1]):
        return None
    a, b = (vs[-2], vs[-1]) if edge == vs[-1] else (vs[1], vs[0])
    if logarithmic:
        return b * (b / a)
    nxt = b + (b - a)
    if nxt >= 0.0:
        return nxt
    return 0.0 if b > 0.0 else None


def search_past_edge(values, best: float, best_score: float, score, steps: int,
                     logarithmic: bool) -> tuple[float, float, list]:
    """A grid search's best value ``best`` (score ``best_score``) on the edge of the ``values``
    tried is not a minimum: score up to ``steps`` more values beyond it (:func:`beyond_edge`),
    ``score(v) -> float``, each kept while it scores lower than the one before. Returns (best, its
    score, every value tried)."""
    tried = list(values)
    for _ in range(steps):
        nxt = beyond_edge(tried, best, logarithmic)
        if nxt is None or nxt in tried:
            break
        s = score(nxt)
        tried.append(nxt)
        if not s < best_score:
            break
        best, best_score = nxt, s
    return best, best_score, tried


@dataclass
class IdentifyConfig:
    """System identification of the physics prior (effect ``physics``) before training: the
    prior's ``coefficient`` (``bend`` compliance by default: how stiff the material is) is set to
    each of ``values`` in turn, the untrained model is rolled out on ``episodes`` training episodes
    (evenly spaced; never the validation ones) and scored like a validation (``run.keep``'s
    criterion: validation loss, or point distance for ``best_points``), and training starts from
    the best value. Empty ``values``: off (the config's value stays). Compliances and damping are
    > 0 (s^2/m, 1/s), friction >= 0.

    ``extend``: a best value on the grid's first or last value is not a minimum, so up to ``extend``
    more values are scored beyond that end, with the end's spacing (the ratio of its two outermost
    values; friction: their difference, never below 0), as long as each new one scores lower than
    the one before (0: the grid only)."""

    coefficient: str = "bend"
    values: list = field(default_factory=list)
    episodes: int = 3
    extend: int = 0

    def validate(self, where: str = "identify") -> None:
        if self.coefficient not in IDENTIFY_COEFFICIENTS:
            raise ConfigError(f"{where}.coefficient: one of {', '.join(IDENTIFY_COEFFICIENTS)}; got {self.coefficient!r}")
        if self.episodes < 1:
            raise ConfigError(f"{where}.episodes: must be >= 1, got {self.episodes}")
        if isinstance(self.extend, bool) or not isinstance(self.extend, int) or self.extend < 0:
            raise ConfigError(f"{where}.extend: an integer >= 0, got {self.extend!r}")
        try:
            vals = [float(v) for v in self.values]
        except (TypeError, ValueError):
            raise ConfigError(f"{where}.values: a list of numbers, got {self.values!r}") from None
        if any(not math.isfinite(v) or v < 0 or (v == 0 and self.coefficient != "friction") for v in vals):
            raise ConfigError(f"{where}.values: finite, > 0 (friction: >= 0); got {self.values!r}")
        if self.extend and len(set(vals)) < 2:
            raise ConfigError(f"{where}.extend: needs at least two different values to continue the grid, got {self.values!r}")
        self.values = vals


#: options removed from the training config, with the value older run folders store in
#: train_config.yaml (accepted and dropped): (section, key) -> that value
RETIRED_TRAIN_KEYS: dict[tuple[str, str], Any] = {("loss", "silhouette_weight"): 0.0, ("identify", "then"): []}


@dataclass
class TrainConfig:
    """A whole training run (see module docstring)."""

    name: str = "custom"
    model: str = "cpu"
    model_overrides: dict = field(default_factory=dict)
    object: str = "rope"
    robot: str = "panda"
    seed: int = 0
    device: str = "auto"
    data: DataConfig = field(default_factory=DataConfig)
    scene: SceneConfig = field(default_factory=SceneConfig)
    loss: LossConfig = field(default_factory=LossConfig)
    schedule: ScheduleConfig = field(default_factory=ScheduleConfig)
    optim: OptimConfig = field(default_factory=OptimConfig)
    run: RunConfig = field(default_factory=RunConfig)
    identify: IdentifyConfig = field(default_factory=IdentifyConfig)

    def validate(self) -> "TrainConfig":
        if self.device not in ("auto", "cpu", "cuda"):
            raise ConfigError(f"device: one of auto, cpu, cuda; got {self.device!r}")
        self.data.validate()
        self.scene.validate()
        self.loss.validate()
        self.schedule.validate()
        self.optim.validate()
        self.run.validate()
        self.identify.validate()
        return self

    def to_dict(self) -> dict:
        return to_dict(self)

    @staticmethod
    def from_dict(data: Mapping[str, Any], where: str = "") -> "TrainConfig":
        return from_dict(TrainConfig, drop_retired_keys(data, RETIRED_TRAIN_KEYS, where), where).validate()

    def to_yaml(self) -> str:
        return yaml.safe_dump(self.to_dict(), sort_keys=False)

    def model_config(self):
        """The simulator's :class:`~soma_ros.core.config.ModelConfig`: ``model`` (name or path)
        with the object's hierarchy, then ``model_overrides`` merged over it."""
        from soma_ros.core.config import ModelConfig, load_model_config

        base = load_model_config(self.model, object=self.object)
        if not self.model_overrides:
            return base
        return ModelConfig.from_dict(merge_config(base.to_dict(), self.model_overrides), "model_overrides.")


def load_train_config(name_or_path: Union[str, Path, Mapping[str, Any]], overrides: Optional[Mapping] = None) -> TrainConfig:
    """``config/train/<name>.yaml``, a YAML path, or a mapping -> :class:`TrainConfig`.

    ``overrides``: nested mapping merged over the file (e.g. ``{"schedule": {"iters_per_epoch": 2}}``).
    """
    if isinstance(name_or_path, Mapping):
        data = dict(name_or_path)
        where = ""
    else:
        p = Path(name_or_path)
        if not (p.suffix in (".yaml", ".yml") and p.is_file()):
            try:
                p = resolve_config(f"train/{name_or_path}")
            except FileNotFoundError:
                p = resolve_config(name_or_path)
        data = read_config(p)  # with its base applied
        data.setdefault("name", p.stem)
        where = f"{p.name}: "
    if overrides:
        data = merge_config(data, overrides)
    return TrainConfig.from_dict(data, where)
