"""Model / object configs: YAML loading, strict validation, merging."""

from __future__ import annotations

import pytest
import yaml

from soma_ros.core.config import (
    ConfigError,
    EffectSpec,
    ModelConfig,
    load_model_config,
    load_object_config,
)
from soma_ros.paths import config_dir


def test_shipped_model_configs_load_and_roundtrip():
    paper = load_model_config("paper")
    cpu = load_model_config("cpu")
    assert (paper.gnn.latent, paper.gnn.layers, paper.gnn.layer_norm) == (128, 16, True)
    assert paper.graph.k == 16 and paper.graph.radii == [0.03, 0.2, 0.5, 5.0]
    assert paper.hierarchy.thresholds == [0.02, 0.2] and paper.num_levels == 4
    assert cpu.gnn.latent <= 48 and cpu.gnn.layers <= 4 and not cpu.gnn.splat_head
    for cfg in (paper, cpu):
        assert [e.name for e in cfg.effects] == ["gravity", "support", "robot"]
        again = ModelConfig.from_dict(yaml.safe_load(yaml.safe_dump(cfg.to_dict())))
        assert again == cfg
    assert load_model_config(config_dir() / "models" / "cpu.yaml") == cpu


@pytest.mark.parametrize("obj", ["rope", "cloth", "doll"])
def test_object_configs_override_hierarchy(obj, tmp_path):
    o = load_object_config(obj)
    assert o.name == obj and o.total_mass > 0 and o.hierarchy.thresholds == [0.02, 0.2]
    custom = tmp_path / "thin.yaml"
    custom.write_text(
        "name: thin\nhierarchy:\n  thresholds: [0.01, 0.05, 0.3]\ngraph_radii: [0.02, 0.1, 0.2, 0.6, 5.0]\n"
    )
    cfg = load_model_config("cpu", object=custom)
    assert cfg.hierarchy.thresholds == [0.01, 0.05, 0.3] and cfg.num_levels == 5
    assert cfg.graph.radii == [0.02, 0.1, 0.2, 0.6, 5.0]
    # more levels without radii for them: a clear error
    bad = tmp_path / "bad.yaml"
    bad.write_text("name: bad\nhierarchy:\n  thresholds: [0.01, 0.05, 0.3]\n")
    with pytest.raises(ConfigError, match="one radius per level"):
        load_model_config("cpu", object=bad)


@pytest.mark.parametrize(
    "patch, message",
    [
        ({"gnn": {"latnet": 3}}, r"gnn\.latnet: unknown key"),
        ({"gnn": {"latent": "big"}}, r"gnn\.latent: expected int"),
        ({"hierarchy": {"thresholds": [0.2, 0.02]}}, "increasing"),
        ({"graph": {"radii": [0.1, 0.2]}}, "one radius per level"),
        ({"graph": {"knn_backend": "faiss"}}, "knn_backend"),
        ({"normalizer": {"mode": "magic"}}, "normalizer.mode"),
        ({"dynamics": {"max_speed": -1.0}}, "max_speed"),
        ({"effects": [{"tau": 0.1}]}, "without 'name'"),
        ({"effects": "gravity"}, "expected a list"),
        ({"simulator": {}}, "unknown key"),
    ],
)
def test_bad_configs_name_the_key(patch, message):
    with pytest.raises(ConfigError, match=message):
        load_model_config(patch)


def test_effect_spec_parsing():
    s = EffectSpec.parse({"name": "support", "tau": 0.02, "key": "table"})
    assert (s.name, s.instance_key, s.params) == ("support", "table", {"tau": 0.02})
    assert EffectSpec.parse("wind").to_yaml_dict() == {"name": "wind"}
    assert s.to_yaml_dict() == {"name": "support", "key": "table", "tau": 0.02}
    with pytest.raises(FileNotFoundError):
        load_model_config("no_such_model")


def test_exponent_floats_read_as_floats():
    """PyYAML reads ``1e-3`` (no dot) as a string; a float field takes it as YAML 1.2 does."""
    patch = yaml.safe_load("dynamics: {max_speed: 2e1}")
    assert patch["dynamics"]["max_speed"] == "2e1"  # the YAML 1.1 quirk this guards against
    assert load_model_config(patch).dynamics.max_speed == 20.0
    with pytest.raises(ConfigError, match=r"dynamics\.max_speed: expected float"):
        load_model_config({"dynamics": {"max_speed": "fast"}})


def test_a_variant_names_its_base_and_only_what_differs(tmp_path):
    from soma_ros.core.config import read_config

    (tmp_path / "base.yaml").write_text("a: 1\nnested: {x: 1, y: [1, 2]}\nkeep: k\n")
    (tmp_path / "mid.yaml").write_text("base: base\nnested: {y: [3]}\n")
    (tmp_path / "top.yaml").write_text("base: mid.yaml\na: 2\n")
    assert read_config(tmp_path / "top.yaml") == {"a": 2, "nested": {"x": 1, "y": [3]}, "keep": "k"}


def test_a_missing_or_looping_base_is_one_clear_error(tmp_path):
    from soma_ros.core.config import ConfigError, read_config

    (tmp_path / "a.yaml").write_text("base: b\n")
    (tmp_path / "b.yaml").write_text("base: a\n")
    (tmp_path / "c.yaml").write_text("base: nowhere\n")
    with pytest.raises(ConfigError, match=r"bases form a loop \(a.yaml -> b.yaml -> a.yaml\)"):
        read_config(tmp_path / "a.yaml")
    with pytest.raises(ConfigError, match="base 'nowhere' not found"):
        read_config(tmp_path / "c.yaml")


def test_a_training_config_variant_is_its_base_plus_what_it_names(tmp_path):
    import yaml

    from soma_ros.paths import resolve_config
    from soma_ros.training.config import load_train_config

    base = resolve_config("train/tiny")
    (tmp_path / "tiny.yaml").write_text(base.read_text())
    (tmp_path / "longer.yaml").write_text(yaml.safe_dump({"base": "tiny", "schedule": {"iters_per_epoch": 7}}))
    a, b = load_train_config(tmp_path / "tiny.yaml"), load_train_config(tmp_path / "longer.yaml")
    assert b.schedule.iters_per_epoch == 7 and b.name == "longer"
    b.schedule.iters_per_epoch, b.name = a.schedule.iters_per_epoch, a.name
    assert b.to_dict() == a.to_dict()


#: shipped variants and their bases (config/<family>/<variant>.yaml says ``base: <base>``)
SHIPPED_VARIANTS = [("discrepancy", "coarse", "default"), ("discrepancy", "fast", "default"),
                    ("discrepancy", "physics", "default"), ("reconstruct", "quality", "cpu"),
                    ("eval", "tiny_mlp", "tiny"), ("train", "tiny_mlp", "tiny"), ("train", "tiny_physics", "tiny"),
                    ("train", "tiny_physics_newton", "tiny_physics"), ("train", "tiny_physics_rod", "tiny_physics_newton"),
                    ("train", "experiments/coupling_feature", "../tiny"),
                    ("train", "experiments/coupling_points", "coupling_feature")]


def _leaves(d) -> int:
    """How many keys a mapping sets, counting those of nested mappings one by one."""
    return sum(_leaves(v) if isinstance(v, dict) else 1 for v in d.values())


@pytest.mark.parametrize("family,variant,base", SHIPPED_VARIANTS)
def test_shipped_variants_name_their_base_and_load(family, variant, base):
    """Each shipped variant names its base, sets fewer keys than the base, and loads through its
    family's loader (unknown keys refused there) to a config that differs from the base's."""
    import yaml

    from soma_ros.core.config import to_dict
    from soma_ros.discrepancy.workflow import load_discrepancy_config
    from soma_ros.evaluation.accuracy import load_bench_config
    from soma_ros.paths import resolve_config
    from soma_ros.scene.splat_fit import load_fit_config

    from soma_ros.training.config import load_train_config

    path = resolve_config(f"{family}/{variant}")
    raw = yaml.safe_load(path.read_text())
    assert raw.get("base") == base
    base_path = (path.parent / f"{base}.yaml").resolve()
    assert _leaves(raw) < _leaves(yaml.safe_load(base_path.read_text()))
    load = {"discrepancy": load_discrepancy_config, "reconstruct": load_fit_config, "eval": load_bench_config,
            "train": load_train_config}[family]
    a, b = to_dict(load(base_path)), to_dict(load(path))
    a.pop("name", None), b.pop("name", None)
    assert a != b
    for key, value in raw.items():  # what the variant names is what it gets
        if key != "base" and not isinstance(value, dict):
            assert b[key] == value, key


def test_every_training_config_but_the_two_bases_is_a_variant():
    """config/train/ holds two bases (tiny for CPU, paper for GPUs); every other file names one."""
    from soma_ros.core.config import read_config

    train = config_dir() / "train"
    for path in sorted(train.rglob("*.yaml")):
        raw = yaml.safe_load(path.read_text())
        if path.stem in ("tiny", "paper") and path.parent == train:
            assert "base" not in raw, path
        else:
            assert "base" in raw, path
            read_config(path)


#: what each training variant resolves to where it differs from ``tiny`` (train config keys, and
#: ``model.`` keys of the simulator config it builds)
_TINY = {"schedule.stage1.length_start": 8, "schedule.stage1.length_growth": 0, "optim.network.lr": 1e-4,
         "optim.network.warmup_iters": 15, "run.keep": "best_score", "loss.depth_weight": 1.0,
         "loss.depth_region": "scored", "loss.points_weight": 0.0, "identify.values": [], "identify.extend": 0,
         "model.gnn.out_init_scale": 0.0, "model.robot.form": "coupling", "model.robot.feature": False,
         "model.physics.solver": None, "model.physics.bend_model": None}
_SHORT = {"schedule.stage1.length_start": 2, "schedule.stage1.length_growth": 2, "optim.network.lr": None,
          "optim.network.warmup_iters": 0, "run.keep": "best", "model.gnn.out_init_scale": 0.1}
_POINTS = {"loss.depth_weight": 0.0, "loss.depth_region": "object", "loss.points_weight": 3.0}
_PHYSICS = {**_SHORT, "model.robot.form": None, "model.robot.feature": None, "model.physics.solver": "jacobi",
            "model.physics.bend_model": "pairs"}
_NEWTON = {**_PHYSICS, "model.gnn.out_init_scale": 0.0, "model.physics.solver": "newton",
           "identify.values": [1e-8, 1e-7, 1e-6, 1e-5, 1e-4]}
_COUPLING = {**_SHORT, "model.robot.feature": True}
TRAIN_VARIANTS = {
    "tiny": {},
    "tiny_mlp": {**_SHORT, **_POINTS, "model.robot.form": "mlp", "model.robot.feature": True},
    "tiny_physics": _PHYSICS,
    "tiny_physics_newton": _NEWTON,
    "tiny_physics_rod": {**_NEWTON, "model.physics.bend_model": "rod", "identify.values": [1.0, 3.0, 10.0, 30.0, 100.0],
                         "identify.extend": 3},
    "experiments/coupling_feature": _COUPLING,
    "experiments/coupling_points": {**_COUPLING, **_POINTS},
}


@pytest.mark.parametrize("name", sorted(TRAIN_VARIANTS))
def test_each_training_config_resolves_to_its_settings(name):
    """Each shipped training config, with its bases applied, gets the settings it is documented with
    (the keys where the variants differ)."""
    from soma_ros.training.config import load_train_config

    cfg = load_train_config(name)
    model = cfg.model_config()
    effects = {e.name: e for e in model.effects}

    def get(key):
        if key.startswith("model.gnn."):
            return getattr(model.gnn, key.split(".")[-1])
        if key.startswith(("model.robot.", "model.physics.")):
            _, effect, attr = key.split(".")
            if effect not in effects:
                return None
            if attr == "feature":
                return effects[effect].feature
            return effects[effect].params.get(attr, {"form": "mlp", "solver": "jacobi", "bend_model": "pairs"}[attr])
        obj = cfg
        for part in key.split("."):
            obj = getattr(obj, part)
        return obj

    expected = {**_TINY, **TRAIN_VARIANTS[name]}
    assert {k: get(k) for k in expected} == expected


def test_a_checkpoint_written_with_a_retired_option_at_its_old_value_loads():
    """Older checkpoints store ``dynamics.direct_splats: false``; they load, and a true one is refused."""
    from soma_ros.core.config import ConfigError, ModelConfig, load_model_config

    d = load_model_config("cpu").to_dict()
    d["dynamics"]["direct_splats"] = False
    assert ModelConfig.from_dict(d).to_dict() == load_model_config("cpu").to_dict()
    d["dynamics"]["direct_splats"] = True
    with pytest.raises(ConfigError, match="direct_splats: this option was removed"):
        ModelConfig.from_dict(d)
