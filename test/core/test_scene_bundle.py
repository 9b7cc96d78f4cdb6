"""scene.json versions: a bundle of this version round-trips; version 1 bundles set up from a
bag (CameraInfo K stored unconverted) are refused with one line; version 1 bundles from a
capture load unchanged."""

import json

import numpy as np
import pytest

from soma_ros.core.scene_bundle import VERSION, SceneBundle
from soma_ros.core.scenes import synthetic_bundle


def _rewrite(folder, **changes):
    meta = json.loads((folder / "scene.json").read_text())
    meta.update(changes)
    (folder / "scene.json").write_text(json.dumps(meta))
    return meta


def test_a_bundle_round_trips_with_its_version_and_cameras(tmp_path):
    b = synthetic_bundle(200, width=32, height=24)
    b.save(tmp_path / "scene")
    assert json.loads((tmp_path / "scene" / "scene.json").read_text())["version"] == VERSION == 2
    back = SceneBundle.load(tmp_path / "scene")
    for c0, c1 in zip(b.cameras, back.cameras):
        assert c0.name == c1.name and np.array_equal(c0.K, c1.K)


def test_a_version_1_bundle_from_a_bag_is_refused_in_one_line(tmp_path):
    b = synthetic_bundle(200, width=32, height=24)
    b.extra = {"source_episode": "ep_000", "source_bag": "data/ep_000"}
    b.save(tmp_path / "scene")
    _rewrite(tmp_path / "scene", version=1)
    with pytest.raises(ValueError, match="version 1, set up from a bag") as exc:
        SceneBundle.load(tmp_path / "scene")
    assert "\n" not in str(exc.value) and str(tmp_path / "scene") in str(exc.value)


def test_a_version_1_bundle_from_a_capture_loads_as_it_is(tmp_path):
    b = synthetic_bundle(200, width=32, height=24)
    b.extra = {"source_scan": "scan.splat", "source_capture": "capture"}
    b.save(tmp_path / "scene")
    _rewrite(tmp_path / "scene", version=1)
    back = SceneBundle.load(tmp_path / "scene")
    assert np.array_equal(back.cameras[0].K, b.cameras[0].K)


@pytest.mark.parametrize("version", [0, 3, None])
def test_an_unknown_version_is_refused(tmp_path, version):
    synthetic_bundle(200, width=32, height=24).save(tmp_path / "scene")
    _rewrite(tmp_path / "scene", version=version)
    with pytest.raises(ValueError, match=f"version {version} is not {VERSION}"):
        SceneBundle.load(tmp_path / "scene")
