"""Model configuration: dataclasses loaded from YAML (``config/models/*.yaml``).

A :class:`ModelConfig` has one section per part of the simulator:

=============  =====================================================================
section        what it configures
=============  =====================================================================
hierarchy      distance thresholds of the cluster levels (:mod:`.hierarchy`)
graph          per-level kNN graphs: k, radii, dynamic edges (:mod:`.graph`)
gnn            the shared hierarchical mesh graph network (:mod:`.gnn`)
dynamics       feature scales and the numerical-safety bounds of the step
normalizer     feature normalisers: fixed, or fitted from data then frozen
effects        the force terms, by registry name with parameters (:mod:`.effects`)
=============  =====================================================================

An object config (``config/objects/*.yaml``, :class:`ObjectConfig`) carries the
per-object hierarchy thresholds (and optionally graph radii);
``load_model_config("cpu", object="rope")`` merges it into the model config.

Loading is strict: an unknown key, a wrong type or a bad value raises
:class:`ConfigError` (a ``ValueError``) naming the key path, e.g.
``gnn.latent: expected int, got 'big'``.
"""

from __future__ import annotations

import dataclasses
import math
import re
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping, Optional, Union

import yaml

from soma_ros.paths import resolve_config
from .errors import ConfigError

#: a decimal number with an exponent and no dot (1e-3, 5E+2), which PyYAML leaves a string
_YAML12_FLOAT = re.compile(r"^[-+]?(\d+\.?\d*|\.\d+)[eE][-+]?\d+$")

__all__ = [
    "ConfigError",
    "HierarchyConfig",
    "GraphConfig",
    "GNNConfig",
    "DynamicsConfig",
    "NormalizerConfig",
    "EffectSpec",
    "ModelConfig",
    "ObjectConfig",
    "load_model_config",
    "load_object_config",
    "from_dict",
    "to_dict",
    "read_config",
    "merge_config",
]


# --------------------------------------------------------------------------- sections
@dataclass
class HierarchyConfig:
    """Cluster levels above the splats (a root node is always added on top).

    ``thresholds[i]`` is the complete-linkage diameter (metres) of cluster level
    i + 1: every two members of one cluster are at most this far apart (see
    :func:`soma_ros.core.hierarchy.complete_linkage_clusters`). Increasing.
    ``seed_fraction`` is the radius of the ball-cover seeds as a fraction of the
    threshold (<= 0.5 so that a seed alone respects the threshold).
    """

    thresholds: list[float] = field(default_factory=lambda: [0.02, 0.2])
    seed_fraction: float = 0.25

    def validate(self, where: str = "hierarchy") -> None:
        if not self.thresholds:
            raise ConfigError(f"{where}.thresholds: need at least one cluster level")
        prev = 0.0
        for i, t in enumerate(self.thresholds):
            if not (math.isfinite(t) and t > prev):
                raise ConfigError(
                    f"{where}.thresholds[{i}]: thresholds must be finite, > 0 and increasing, "
                    f"got {self.thresholds}"
                )
            prev = t
        if not (0.0 < self.seed_fraction <= 0.5):
            raise ConfigError(f"{where}.seed_fraction: must lie in (0, 0.5], got {self.seed_fraction}")

    @property
    def num_levels(self) -> int:
        """Levels including splats (level 0) and the root (last level)."""
        return len(self.thresholds) + 2


@dataclass
class GraphConfig:
    """Per-level graphs: kNN (k) filtered by a radius.

    ``radii`` has one radius per level, splats first, root last (the public
    SoMA code uses [0.03, 0.2, 0.5, 5.0]); the splat-level radius is used only
    where a splat-level graph is asked for. ``dynamic_edges`` adds, at every
    cluster level, the current-shape kNN pairs within ``dynamic_radii`` (default:
    ``radii``) that are not static edges; they are recomputed every
    ``dynamic_every`` steps (1 = every step). ``knn_backend``: "auto" (scipy
    cKDTree for CPU tensors, chunked torch cdist on CUDA), "scipy" or "torch".
    """

    k: int = 16
    radii: list[float] = field(default_factory=lambda: [0.03, 0.2, 0.5, 5.0])
    dynamic_edges: bool = True
    dynamic_radii: Optional[list[float]] = None
    dynamic_every: int = 1
    knn_backend: str = "auto"

    def validate(self, num_levels: int, where: str = "graph") -> None:
        if self.k < 1:
            raise ConfigError(f"{where}.k: must be >= 1, got {self.k}")
        for name in ("radii", "dynamic_radii"):
            r = getattr(self, name)
            if r is None:
                continue
            if len(r) != num_levels:
                raise ConfigError(
                    f"{where}.{name}: need one radius per level ({num_levels}: splats, "
                    f"{num_levels - 2} cluster level(s), root), got {len(r)}"
                )
            if any(not (math.isfinite(x) and x > 0) for x in r):
                raise ConfigError(f"{where}.{name}: radii must be finite and > 0, got {r}")
        if self.dynamic_every < 1:
            raise ConfigError(f"{where}.dynamic_every: must be >= 1, got {self.dynamic_every}")
        if self.knn_backend not in ("auto", "scipy", "torch"):
            raise ConfigError(f"{where}.knn_backend: one of auto, scipy, torch; got {self.knn_backend!r}")


@dataclass
class GNNConfig:
    """The hierarchical mesh graph network (weights shared across levels).

    ``latent`` x ``layers`` message-passing blocks (paper: 128 x 16), each MLP
    with ``mlp_hidden_layers`` hidden layers and SiLU; ``layer_norm`` applies a
    pre-LayerNorm to node and edge latents in every block. ``attr_dim`` learned
    per-splat attributes (paper: 5). ``top_down_latent`` adds the anchor's final
    latent to a node's encoding (coarse-to-fine information flow).
    ``edge_updates``: MeshGraphNets edge-latent residual stream (paper); off =
    edges keep their encoding and messages are recomputed from it in every
    block (about half the per-edge work; the ``cpu`` model).
    ``splat_head``: decode per-splat updates with a light MLP on [splat
    encoding, anchor latent] (paper); off = splats are moved only by their
    anchors' deformation. ``out_init_scale`` multiplies the initial weights of
    the last decoder layer (small: a fresh model responds gently).
    """

    latent: int = 128
    layers: int = 16
    mlp_hidden_layers: int = 1
    layer_norm: bool = True
    edge_updates: bool = True
    attr_dim: int = 5
    top_down_latent: bool = True
    splat_head: bool = False
    out_init_scale: float = 0.1

    def validate(self, where: str = "gnn") -> None:
        if self.latent < 1 or self.layers < 0 or self.mlp_hidden_layers < 0 or self.attr_dim < 0:
            raise ConfigError(
                f"{where}: latent >= 1, layers >= 0, mlp_hidden_layers >= 0, attr_dim >= 0 required; got "
                f"latent={self.latent} layers={self.layers} mlp_hidden_layers={self.mlp_hidden_layers} "
                f"attr_dim={self.attr_dim}"
            )
        if not (self.out_init_scale >= 0 and math.isfinite(self.out_init_scale)):
            raise ConfigError(f"{where}.out_init_scale: must be finite and >= 0, got {self.out_init_scale}")


@dataclass
class DynamicsConfig:
    """Feature scales and numerical-safety bounds of one simulator step.

    ``accel_scale`` (m/s^2) divides acceleration/force-per-mass features and
    multiplies the acceleration head; ``velocity_scale`` (m/s) divides velocity
    features. Bounds (see :mod:`.simulator`): a node's velocity relative to its
    anchor is at most ``max_speed`` m/s; each log singular value of a per-step
    deformation is at most ``max_log_stretch`` before centring (so |log s| <=
    2 max_log_stretch after); a node's residual offset from the position its
    anchor carries it to is at most ``residual_factor`` x its anchor's rest
    radius.

    ``passive_friction`` (None = off; the default, and what every training config uses):
    the *passive object* rule at the root (see :mod:`.simulator`). On a step where every
    force but gravity and the support is zero or integrated directly (``direct`` effects),
    the network may not raise the root's horizontal speed or its upward speed, and while
    the object touches the support (its lowest splat within ``passive_contact_m`` of its
    lowest height in the episode's initial state) Coulomb friction with coefficient
    ``passive_friction`` brakes the horizontal speed.

    ``passive_exempt`` (effect keys; default none): a step on which one of these terms exerts a
    force is not passive, though the term is direct. For the terms the model was trained with
    (e.g. its direct robot coupling): their steps are inside its training data, where no such
    rule acted, and the rule's friction added on top of the learned drag doubled the resimulated
    rope's error (docs/discrepancy.md). Terms added later (a candidate wind) stay bounded by it.
    ``passive_exempt_closed``: the exemption holds only while the gripper is closed (gripper
    state < 0.5), where the coupling carries the object; with the gripper open the step stays
    passive (an open gripper's coupling drags, it does not carry, and exempting it let the
    network lift a released rope under the hovering gripper: docs/design_decisions.md, "Model and simulator").

    """

    accel_scale: float = 9.81
    velocity_scale: float = 1.0
    max_speed: float = 2.0
    max_log_stretch: float = 0.25
    residual_factor: float = 2.0
    passive_friction: Optional[float] = None
    passive_contact_m: float = 0.01
    passive_exempt: list[str] = field(default_factory=list)
    passive_exempt_closed: bool = False

    def validate(self, where: str = "dynamics") -> None:
        for name in ("accel_scale", "velocity_scale", "max_speed", "max_log_stretch", "residual_factor",
                     "passive_contact_m"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ConfigError(f"{where}.{name}: must be finite and > 0, got {v}")
        pf = self.passive_friction
        if pf is not None and not (math.isfinite(pf) and pf >= 0):
            raise ConfigError(f"{where}.passive_friction: must be None (off) or finite and >= 0, got {pf}")
        if not all(isinstance(k, str) and k for k in self.passive_exempt):
            raise ConfigError(f"{where}.passive_exempt: must be a list of effect keys, got {self.passive_exempt!r}")
        if not isinstance(self.passive_exempt_closed, bool):
            raise ConfigError(f"{where}.passive_exempt_closed: must be true or false, got {self.passive_exempt_closed!r}")

    def passive_rule_text(self) -> str:
        """The passive-object rule in words, for logs."""
        if self.passive_friction is None:
            return "off"
        if not self.passive_exempt:
            return f"friction {self.passive_friction}, on every step"
        grip = " with the gripper closed" if self.passive_exempt_closed else ""
        return f"friction {self.passive_friction}, not on steps where {', '.join(self.passive_exempt)} acts{grip}"


@dataclass
class NormalizerConfig:
    """Feature normalisers. ``fixed``: identity (features are pre-scaled by
    physical scales). ``fit``: running mean/std accumulated in training mode
    over the first ``max_count`` rows, then frozen; stored in checkpoints."""

    mode: str = "fixed"
    max_count: int = 1_000_000
    eps: float = 1e-6

    def validate(self, where: str = "normalizer") -> None:
        if self.mode not in ("fixed", "fit"):
            raise ConfigError(f"{where}.mode: one of fixed, fit; got {self.mode!r}")
        if self.max_count < 1 or not self.eps > 0:
            raise ConfigError(f"{where}: max_count >= 1 and eps > 0 required")


@dataclass
class EffectSpec:
    """One force term: registry ``name``, instance ``key`` (default: name),
    ``trainable`` (False freezes its parameters), ``direct`` and its ``params``.

    ``direct`` (default False): besides entering the network as a force-per-mass
    feature (every effect does), the term's force is integrated by the
    simulator as an explicit acceleration on top of the learned dynamics
    (residual physics; see :mod:`soma_ros.core.simulator`). Not allowed for
    the reference effects (gravity, support). Written to YAML / checkpoints
    only when True, so configs without it are unchanged.

    ``feature`` (default True): whether the network sees the term's force in its
    F/m feature. ``feature: false`` (only with ``direct: true``) makes the term
    pure physics: integrated explicitly, invisible to the network, which then
    responds only to the motion it causes (e.g. how the rest of a rope follows
    the part a gripper drags), not to the force itself.

    ``fitted_after_training`` (default False): the term was added to a trained model and only its
    own parameters fitted, the network frozen (the discrepancy workflow's named effect). It is
    not one of the model's trained terms (:meth:`Simulator.trained_terms`), so the passive-object
    rule's exemption never covers it: it was fitted under the rule. Written only when True.

    In YAML an effect is a mapping whose other keys are the params::

        - name: support
          tau: 0.01
        - name: wind
          direct: true
    """

    name: str
    key: Optional[str] = None
    trainable: bool = True
    params: dict = field(default_factory=dict)
    direct: bool = False
    feature: bool = True
    fitted_after_training: bool = False

    @property
    def instance_key(self) -> str:
        return self.key or self.name

    @staticmethod
    def parse(item: Union[str, Mapping[str, Any], "EffectSpec"], where: str = "effects") -> "EffectSpec":
        if isinstance(item, EffectSpec):
            return item
        if isinstance(item, str):
            return EffectSpec(name=item)
        if not isinstance(item, Mapping):
            raise ConfigError(f"{where}: an effect is a name or a mapping with 'name', got {item!r}")
        d = dict(item)
        if "name" not in d:
            raise ConfigError(f"{where}: effect mapping without 'name': {item!r}")
        name = d.pop("name")
        key = d.pop("key", None)
        trainable = d.pop("trainable", True)
        direct = d.pop("direct", False)
        feature = d.pop("feature", True)
        post_hoc = d.pop("fitted_after_training", False)
        params = dict(d.pop("params", {}) or {})
        params.update(d)
        if not isinstance(name, str) or (key is not None and not isinstance(key, str)):
            raise ConfigError(f"{where}: 'name' and 'key' must be strings, got {item!r}")
        if not isinstance(trainable, bool):
            raise ConfigError(f"{where}.trainable: expected bool, got {trainable!r}")
        if not isinstance(direct, bool):
            raise ConfigError(f"{where}.direct: expected bool, got {direct!r}")
        if not isinstance(feature, bool):
            raise ConfigError(f"{where}.feature: expected bool, got {feature!r}")
        if not isinstance(post_hoc, bool):
            raise ConfigError(f"{where}.fitted_after_training: expected bool, got {post_hoc!r}")
        if not feature and not direct:
            raise ConfigError(f"{where}: effect {name!r} with feature: false must be direct: true (else it acts on nothing)")
        return EffectSpec(name=name, key=key, trainable=trainable, params=params, direct=direct, feature=feature,
                          fitted_after_training=post_hoc)

    def to_yaml_dict(self) -> dict:
        d: dict[str, Any] = {"name": self.name}
        if self.key is not None:
            d["key"] = self.key
        if not self.trainable:
            d["trainable"] = False
        if self.direct:
            d["direct"] = True
        if not self.feature:
            d["feature"] = False
        if self.fitted_after_training:
            d["fitted_after_training"] = True
        d.update(self.params)
        return d


def _default_effects() -> list[EffectSpec]:
    return [EffectSpec("gravity"), EffectSpec("support"), EffectSpec("robot")]



#: options removed from the model config, with the value that older checkpoints store (and that
#: a load accepts and drops): (section, key) -> the value it always had in a shipped config
RETIRED_MODEL_KEYS: dict[tuple[str, str], Any] = {("dynamics", "direct_splats"): False}


def drop_retired_keys(data: Mapping[str, Any], retired: Mapping[tuple[str, str], Any], where: str = "") -> dict:
    """``data`` without the removed options of ``retired`` ((section, key) -> the only value
    accepted: the one older files store); any other value of one is refused in one line."""
    data = dict(data)
    for (section, key), off in retired.items():
        sub = data.get(section)
        if isinstance(sub, Mapping) and key in sub:
            if sub[key] != off:
                raise ConfigError(f"{where}{section}.{key}: this option was removed (only {off!r} is accepted, "
                                  f"as older checkpoints and run folders store it)")
            data[section] = {k: v for k, v in sub.items() if k != key}
    return data

@dataclass
class ModelConfig:
    """The whole simulator configuration (see module docstring)."""

    name: str = "custom"
    hierarchy: HierarchyConfig = field(default_factory=HierarchyConfig)
    graph: GraphConfig = field(default_factory=GraphConfig)
    gnn: GNNConfig = field(default_factory=GNNConfig)
    dynamics: DynamicsConfig = field(default_factory=DynamicsConfig)
    normalizer: NormalizerConfig = field(default_factory=NormalizerConfig)
    effects: list[EffectSpec] = field(default_factory=_default_effects)

    def validate(self) -> "ModelConfig":
        self.hierarchy.validate()
        self.graph.validate(self.hierarchy.num_levels)
        self.gnn.validate()
        self.dynamics.validate()
        self.normalizer.validate()
        keys = [e.instance_key for e in self.effects]
        dup = sorted({k for k in keys if keys.count(k) > 1})
        if dup:
            raise ConfigError(f"effects: duplicate effect keys {dup} (give one of them a 'key')")
        return self

    @property
    def num_levels(self) -> int:
        return self.hierarchy.num_levels

    def to_dict(self) -> dict:
        d = to_dict(self)
        d["effects"] = [e.to_yaml_dict() for e in self.effects]
        return d

    @staticmethod
    def from_dict(data: Mapping[str, Any], where: str = "") -> "ModelConfig":
        data = drop_retired_keys(data, RETIRED_MODEL_KEYS, where)
        effects = data.pop("effects", None)
        cfg = from_dict(ModelConfig, data, where)
        if effects is not None:
            if not isinstance(effects, list):
                raise ConfigError(f"{where}effects: expected a list, got {type(effects).__name__}")
            cfg.effects = [EffectSpec.parse(e, f"{where}effects[{i}]") for i, e in enumerate(effects)]
        return cfg.validate()


@dataclass
class ObjectConfig:
    """Per-object settings (``config/objects/<name>.yaml``)."""

    name: str
    description: str = ""
    total_mass: float = 0.1
    hierarchy: HierarchyConfig = field(default_factory=HierarchyConfig)
    graph_radii: Optional[list[float]] = None

    def validate(self) -> "ObjectConfig":
        self.hierarchy.validate(f"object {self.name}: hierarchy")
        if not (math.isfinite(self.total_mass) and self.total_mass > 0):
            raise ConfigError(f"object {self.name}: total_mass must be > 0, got {self.total_mass}")
        if self.graph_radii is not None:
            GraphConfig(radii=list(self.graph_radii)).validate(
                self.hierarchy.num_levels, f"object {self.name}: graph_radii"
            )
        return self


# --------------------------------------------------------------------------- generic (de)serialisation
def _type_name(tp: Any) -> str:
    return getattr(tp, "__name__", str(tp))


def _convert(value: Any, tp: Any, where: str) -> Any:
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if tp is Any:
        return value
    if origin is Union:
        if value is None and type(None) in args:
            return None
        errors = []
        for a in args:
            if a is type(None):
                continue
            try:
                return _convert(value, a, where)
            except ConfigError as exc:
                errors.append(str(exc))
        raise ConfigError(errors[0] if errors else f"{where}: bad value {value!r}")
    if dataclasses.is_dataclass(tp):
        if not isinstance(value, Mapping):
            raise ConfigError(f"{where}: expected a mapping for {_type_name(tp)}, got {value!r}")
        return from_dict(tp, value, f"{where}.")
    if origin in (list, tuple):
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{where}: expected a list, got {value!r}")
        item_tp = args[0] if args else Any
        return [_convert(v, item_tp, f"{where}[{i}]") for i, v in enumerate(value)]
    if origin is dict or tp is dict:
        if not isinstance(value, Mapping):
            raise ConfigError(f"{where}: expected a mapping, got {value!r}")
        return dict(value)
    if tp is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{where}: expected bool, got {value!r}")
        return value
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{where}: expected int, got {value!r}")
        return value
    if tp is float:
        if isinstance(value, str) and _YAML12_FLOAT.match(value.strip()):
            return float(value)  # YAML 1.1 (PyYAML) reads 1e-3 as a string; YAML 1.2 and users mean a float
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{where}: expected float, got {value!r}")
        return float(value)
    if tp is str:
        if not isinstance(value, str):
            raise ConfigError(f"{where}: expected str, got {value!r}")
        return value
    return value


def from_dict(cls: type, data: Mapping[str, Any], where: str = "") -> Any:
    """Build dataclass ``cls`` from a mapping; unknown keys and bad types raise ConfigError."""
    if not isinstance(data, Mapping):
        raise ConfigError(f"{where or cls.__name__}: expected a mapping, got {type(data).__name__}")
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls) if f.init}
    unknown = sorted(set(data) - names)
    if unknown:
        raise ConfigError(
            f"{where}{unknown[0]}: unknown key for {cls.__name__} (known: {', '.join(sorted(names))})"
        )
    kwargs = {k: _convert(v, hints[k], f"{where}{k}") for k, v in data.items()}
    try:
        return cls(**kwargs)
    except TypeError as exc:  # missing required field
        raise ConfigError(f"{where.rstrip('.') or cls.__name__}: {exc}") from None


def to_dict(obj: Any) -> Any:
    """Dataclass -> plain dict/list/scalars (YAML- and torch.load(weights_only)-safe)."""
    if dataclasses.is_dataclass(obj):
        return {f.name: to_dict(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if isinstance(obj, (list, tuple)):
        return [to_dict(v) for v in obj]
    if isinstance(obj, dict):
        return {str(k): to_dict(v) for k, v in obj.items()}
    return obj


def merge_config(base: Mapping[str, Any], over: Mapping[str, Any]) -> dict:
    """``over`` merged into ``base``: mappings merge key by key, anything else (lists too)
    is replaced."""
    out = dict(base)
    for key, value in over.items():
        if isinstance(value, Mapping) and isinstance(out.get(key), Mapping):
            out[key] = merge_config(out[key], value)
        else:
            out[key] = value
    return out


def read_config(path: Union[str, Path], _chain: tuple = ()) -> dict:
    """A YAML config file as a mapping, with its ``base:`` applied.

    A variant names its base (``base: tiny``: a file of the same folder, with or without
    ``.yaml``, or a path relative to that folder) and writes only what differs; the base's
    mapping is read the same way (bases may chain) and the variant is merged over it
    (:func:`merge_config`). The returned mapping has no ``base`` key.
    """
    path = Path(path)
    key = path.resolve()
    if key in _chain:
        names = " -> ".join(p.name for p in (*_chain, key))
        raise ConfigError(f"{path}: its bases form a loop ({names})")
    try:
        with open(path) as f:
            data = yaml.safe_load(f)
    except yaml.YAMLError as exc:
        raise ConfigError(f"{path}: invalid YAML: {' '.join(str(exc).split())}") from None
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read: {exc.strerror}") from None
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: expected a mapping at the top level")
    base = data.pop("base", None)
    if base is None:
        return data
    if not isinstance(base, str) or not base:
        raise ConfigError(f"{path}: base must be the name of a config file, got {base!r}")
    cands = [path.parent / base, path.parent / f"{base}.yaml"]
    found = next((c for c in cands if c.is_file()), None)
    if found is None:
        raise ConfigError(f"{path}: base {base!r} not found next to it")
    return merge_config(read_config(found, (*_chain, key)), data)


def _read_yaml(path: Path) -> dict:
    return read_config(path)


def _resolve(name_or_path: Union[str, Path], folder: str) -> Path:
    p = Path(name_or_path)
    if p.suffix in (".yaml", ".yml") and p.is_file():
        return p
    try:
        return resolve_config(f"{folder}/{name_or_path}")
    except FileNotFoundError:
        return resolve_config(name_or_path)


def load_object_config(name_or_path: Union[str, Path]) -> ObjectConfig:
    """``config/objects/<name>.yaml`` (or a path) -> :class:`ObjectConfig`."""
    path = _resolve(name_or_path, "objects")
    data = _read_yaml(path)
    data.setdefault("name", path.stem)
    return from_dict(ObjectConfig, data, f"{path.name}: ").validate()


def load_model_config(
    name_or_path: Union[str, Path, Mapping[str, Any]] = "cpu",
    object: Union[None, str, Path, ObjectConfig] = None,  # noqa: A002 - the natural name
) -> ModelConfig:
    """Model config by name (``config/models/<name>.yaml``), path, or mapping.

    With ``object`` (name, path or :class:`ObjectConfig`) the object's
    hierarchy thresholds (and graph radii, if it sets them) replace the model's.
    """
    if isinstance(name_or_path, Mapping):
        cfg = ModelConfig.from_dict(name_or_path)
    else:
        path = _resolve(name_or_path, "models")
        data = _read_yaml(path)
        data.setdefault("name", path.stem)
        cfg = ModelConfig.from_dict(data, f"{path.name}: ")
    if object is not None:
        obj = object if isinstance(object, ObjectConfig) else load_object_config(object)
        cfg.hierarchy = dataclasses.replace(obj.hierarchy, thresholds=list(obj.hierarchy.thresholds))
        if obj.graph_radii is not None:
            cfg.graph.radii = list(obj.graph_radii)
        if cfg.graph.dynamic_radii is not None and len(cfg.graph.dynamic_radii) != cfg.num_levels:
            raise ConfigError(
                f"object {obj.name} has {cfg.num_levels} levels but graph.dynamic_radii has "
                f"{len(cfg.graph.dynamic_radii)} entries"
            )
        cfg.validate()
    return cfg
