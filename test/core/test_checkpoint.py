"""Checkpoints: atomic save, load from the file alone, bit-identical rollouts."""

from __future__ import annotations

import math
import os

import pytest
import torch

from soma_ros.core.checkpoint import content_checksum, load_checkpoint, read_checkpoint, save_checkpoint
from soma_ros.core.config import load_model_config
from soma_ros.core.scenes import synthetic_rope
from soma_ros.core.simulator import RobotAction, SceneContext, Simulator

torch.set_num_threads(1)


def _actions(sp, n=12):
    cp0 = sp.means[sp.means[:, 0] > 0.15][:30].clone()
    return [RobotAction(cp0 + torch.tensor([0.0, 0.003 * i, 0.002 * i]), 0.5 + 0.4 * math.sin(i)) for i in range(n)]


def _trained_looking_model(model="cpu"):
    torch.manual_seed(7)
    sp = synthetic_rope(1500, seed=8, center=(0.0, 0.0, 0.0))
    sim = Simulator(load_model_config(model))
    sim.add_effect({"name": "wind", "accel": [0.1, 0.0, 0.0]})
    sim.train()
    with torch.no_grad():  # fit the normalisers a little so that their statistics matter
        sim.rollout(sim.init_state(sp, SceneContext.table()), _actions(sp, 4))
        sim.splat_attrs.normal_()
    sim.eval()
    return sp, sim


def _rollout(sim, sp, scene):
    with torch.no_grad():
        return sim.rollout(sim.init_state(sp, scene), _actions(sp))


@pytest.mark.parametrize("model", ["cpu", "paper"])
def test_roundtrip_gives_bit_identical_rollouts(tmp_path, model):
    sp, sim = _trained_looking_model(model)
    assert float(sim.node_norms[1].count) > 0
    scene = SceneContext.table(dt=1 / 15)
    ref = _rollout(sim, sp, scene)
    path = save_checkpoint(tmp_path / "ckpt" / "model.pt", sim, extra={"step": 12, "note": "test"})
    assert path.is_file()
    assert [p.name for p in path.parent.iterdir()] == ["model.pt"]  # no temp file left behind
    loaded = load_checkpoint(path).eval()
    assert loaded.checkpoint_extra == {"step": 12, "note": "test"}
    assert loaded.config.to_dict() == sim.config.to_dict()
    assert [e.instance_key for e in loaded.config.effects] == ["gravity", "support", "robot", "wind"]
    assert loaded.hierarchy.sizes == sim.hierarchy.sizes
    for a, b in zip(sim.state_dict().items(), loaded.state_dict().items()):
        assert a[0] == b[0] and torch.equal(a[1], b[1]), a[0]
    got = _rollout(loaded, sp, scene)
    for s1, s2 in zip(ref, got):
        assert torch.equal(s1.means, s2.means)
        assert torch.equal(s1.covs, s2.covs)
        assert torch.equal(s1.quats, s2.quats)
    assert float((ref[-1].means - sp.means).norm(dim=-1).max()) > 1e-5  # a real rollout, not at rest


def test_save_is_atomic_and_bad_files_fail_clearly(tmp_path, monkeypatch):
    sp, sim = _trained_looking_model()
    path = tmp_path / "m.pt"
    save_checkpoint(path, sim, extra={"v": 1})
    before = path.read_bytes()

    def boom(*a, **k):
        raise OSError("disk full")

    monkeypatch.setattr(os, "replace", boom)
    with pytest.raises(OSError, match="disk full"):
        save_checkpoint(path, sim, extra={"v": 2})
    monkeypatch.undo()
    assert path.read_bytes() == before  # old checkpoint intact
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.pt"]  # temp file cleaned up
    with pytest.raises(TypeError, match="cannot go into a checkpoint"):
        save_checkpoint(path, sim, extra={"obj": object()})
    with pytest.raises(FileNotFoundError):
        load_checkpoint(tmp_path / "missing.pt")
    junk = tmp_path / "junk.pt"
    junk.write_bytes(b"not a checkpoint")
    with pytest.raises(ValueError, match="not a readable soma_ros checkpoint"):
        load_checkpoint(junk)
    other = tmp_path / "other.pt"
    torch.save({"format": "something/else"}, other)
    with pytest.raises(ValueError, match="not a soma_ros simulator checkpoint"):
        load_checkpoint(other)
    payload = read_checkpoint(path)
    payload["state_dict"].pop("gnn.decoder.net.0.weight")
    payload["checksum"] = content_checksum(payload)  # a well-formed file that does not match its config
    broken = tmp_path / "broken.pt"
    torch.save(payload, broken)
    with pytest.raises(ValueError, match="missing"):
        load_checkpoint(broken)


def test_unbound_model_roundtrips(tmp_path):
    sim = Simulator(load_model_config("cpu"))
    path = save_checkpoint(tmp_path / "fresh.pt", sim)
    loaded = load_checkpoint(path)
    assert not loaded.is_bound
    sp = synthetic_rope(400, seed=1)
    with torch.no_grad():
        a = sim.rollout(sim.init_state(sp, SceneContext.table()), _actions(sp, 3))[-1]
        b = loaded.rollout(loaded.init_state(sp, SceneContext.table()), _actions(sp, 3))[-1]
    assert torch.equal(a.means, b.means)


def test_an_effect_parameter_added_later_keeps_its_config_value_with_a_warning(tmp_path):
    """A checkpoint written before an effect gained a parameter (gripper_slip's weaken)
    still loads: the new parameter keeps the value its spec gives (0: no change), with a warning
    naming it; a missing network weight is still an error (test above)."""
    sim = Simulator(load_model_config("cpu"))
    sim.add_effect({"name": "gripper_slip", "direct": True, "loosen": 0.5, "weaken": 0.7})
    path = save_checkpoint(tmp_path / "new.pt", sim)
    payload = read_checkpoint(path)
    assert float(payload["state_dict"]["effects.terms.gripper_slip.weaken"]) == pytest.approx(0.7)
    payload["state_dict"].pop("effects.terms.gripper_slip.weaken")
    for spec in payload["model_config"]["effects"]:  # as written before the parameter existed
        if isinstance(spec, dict) and spec.get("name") == "gripper_slip":
            spec.pop("weaken", None)
    payload["checksum"] = content_checksum(payload)
    old = tmp_path / "old.pt"
    torch.save(payload, old)
    with pytest.warns(UserWarning, match="gripper_slip.weaken"):
        loaded = load_checkpoint(old)
    assert float(loaded.effects["gripper_slip"].weaken.detach()) == 0.0
    assert float(loaded.effects["gripper_slip"].loosen.detach()) == pytest.approx(0.5)


def _flip_tensor_bytes(path, n=100):
    """Flip ``n`` bytes inside the largest tensor record of a torch zip archive (in place)."""
    import zipfile

    with zipfile.ZipFile(path) as z:
        info = max((i for i in z.infolist() if "/data/" in i.filename), key=lambda i: i.file_size)
    raw = bytearray(path.read_bytes())
    # the record's data follows its 30-byte local header, file name and extra field
    name_len = int.from_bytes(raw[info.header_offset + 26: info.header_offset + 28], "little")
    extra_len = int.from_bytes(raw[info.header_offset + 28: info.header_offset + 30], "little")
    start = info.header_offset + 30 + name_len + extra_len
    for i in range(n):
        raw[start + (i * 37) % info.file_size] ^= 0x5A
    path.write_bytes(bytes(raw))


def test_a_checkpoint_with_flipped_bytes_is_refused_naming_the_file(tmp_path):
    """100 flipped bytes in the weights: torch still unpickles the file, the content checksum
    does not match, and the load fails with one line that names the file."""
    _, sim = _trained_looking_model()
    path = save_checkpoint(tmp_path / "m.pt", sim)
    assert read_checkpoint(path)["checksum"].startswith("sha256:")
    _flip_tensor_bytes(path)
    with pytest.raises(ValueError) as err:
        load_checkpoint(path)
    msg = str(err.value)
    assert str(path) in msg and "\n" not in msg
    assert "SHA-256" in msg or "not a readable" in msg
    truncated = tmp_path / "t.pt"
    truncated.write_bytes((tmp_path / "m.pt").read_bytes()[:5000])
    with pytest.raises(ValueError, match="not a readable soma_ros checkpoint") as err:
        load_checkpoint(truncated)
    assert str(truncated) in str(err.value) and "\n" not in str(err.value)


def test_a_checkpoint_without_a_checksum_loads_with_a_warning(tmp_path):
    _, sim = _trained_looking_model()
    path = save_checkpoint(tmp_path / "m.pt", sim)
    payload = read_checkpoint(path)
    payload.pop("checksum")
    old = tmp_path / "old.pt"
    torch.save(payload, old)
    with pytest.warns(UserWarning, match="without a content checksum"):
        load_checkpoint(old)


def test_train_state_checksum_and_fallback_to_the_previous_state(tmp_path):
    """save_train_state keeps the replaced state; a corrupt or truncated newest state makes
    load_train_state fall back to it and say so; both unreadable is one error naming both."""
    from soma_ros.core.checkpoint import load_train_state, previous_state_path, save_train_state

    fmt = "soma_ros.train_state/1"
    path = tmp_path / "train_state.pt"
    assert load_train_state(path, fmt) is None
    for it in (10, 20):
        save_train_state({"format": fmt, "iteration": it, "model": {"w": torch.randn(4000)}}, path)
    prev = previous_state_path(path)
    assert prev.name == "train_state.prev.pt" and torch.load(prev, weights_only=True)["iteration"] == 10
    assert load_train_state(path, fmt)["iteration"] == 20
    said = []
    _flip_tensor_bytes(path)
    got = load_train_state(path, fmt, log=said.append)
    assert got["iteration"] == 10
    assert len(said) == 1 and str(path) in said[0] and "previous training state train_state.prev.pt" in said[0]
    path.write_bytes(prev.read_bytes()[:3000])  # truncated newest
    said.clear()
    assert load_train_state(path, fmt, log=said.append)["iteration"] == 10 and "not a readable" in said[0]
    prev.write_bytes(b"garbage")
    with pytest.raises(ValueError, match="no readable training state") as err:
        load_train_state(path, fmt)
    assert str(path) in str(err.value) and str(prev) in str(err.value) and "\n" not in str(err.value)
