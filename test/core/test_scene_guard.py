"""Scene checks without ROS: the path policy, cloud layouts, physical plausibility, bounded reads."""

from __future__ import annotations

import os

import numpy as np
import pytest
import torch

from soma_ros.core.cloud_layout import REQUIRED_FIELDS, SPLAT_FIELDS, FieldSpec, splat_field_specs
from soma_ros.core.scene_guard import (
    GENERIC_REFUSAL,
    SceneExtent,
    SceneLimits,
    ScenePathPolicy,
    SceneRefused,
    check_cloud_layout,
    check_physical,
    read_scene_file,
)
from soma_ros.core.ply import write_ply, write_splat
from soma_ros.core.scenes import synthetic_rope

torch.set_num_threads(1)


class Cloud:
    """A PointCloud2-shaped object (the checks take anything with these attributes)."""

    def __init__(self, n, fields=None, step=64, data=None, height=1, row_step=None, is_bigendian=False):
        self.width, self.height, self.point_step = n, height, step
        self.row_step = step * n if row_step is None else row_step
        self.fields = fields if fields is not None else splat_field_specs()
        self.data = bytes(step * n * height) if data is None else data
        self.is_bigendian = is_bigendian


LIM = SceneLimits()


def _check(cloud):
    return check_cloud_layout(cloud, LIM, REQUIRED_FIELDS, SPLAT_FIELDS)


def test_cloud_layouts_are_checked_from_the_header_fields_only():
    assert _check(Cloud(10)) == 10
    bad = [
        (Cloud(0), "0 points"),
        (Cloud(200_001, data=b""), "200001 points, more than max_splats (200000)"),  # no data needed to refuse
        (Cloud(10, data=bytes(100)), "data holds 100 bytes, expected width * height * point_step = 640"),
        (Cloud(10, row_step=10), "row_step 10 is not width * point_step (640)"),
        (Cloud(10, step=0, data=b""), "point_step must be > 0"),
        (Cloud(10, is_bigendian=True), "big-endian"),
        (Cloud(10, fields=[FieldSpec(f.name, f.offset, 2 if f.name == "scale_1" else 7) for f in splat_field_specs()]),
         "field 'scale_1' must be FLOAT32 (7) with count 1, got datatype 2 count 1"),
        (Cloud(10, fields=[FieldSpec(f.name, 0, 7) for f in splat_field_specs()]), "overlap"),
        (Cloud(10, fields=[FieldSpec("x", 0, 7, 3)] + splat_field_specs()[1:]), "count 3"),
        (Cloud(10, fields=splat_field_specs()[:-1] + [FieldSpec("mass", 62, 7)]), "overruns point_step 64"),
        (Cloud(10, fields=splat_field_specs() + [FieldSpec("x", 0, 7)]), "declares a field twice"),
        (Cloud(10, fields=[f for f in splat_field_specs() if f.name != "rot_w"]), "lacks required fields: rot_w"),
        (Cloud(10, fields=splat_field_specs()[:-1] + [FieldSpec("mass", 60, 9)]), "unknown datatype 9"),
    ]
    for cloud, reason in bad:
        with pytest.raises(SceneRefused, match=None) as err:
            _check(cloud)
        assert reason in str(err.value), (reason, str(err.value))


def test_physical_checks_are_relative_to_the_starting_scene():
    start = synthetic_rope(500, seed=1)
    ref = SceneExtent.of(start)
    check_physical(synthetic_rope(700, seed=2), ref, LIM)  # another rope: fine
    big = synthetic_rope(300, seed=3)
    big.scales = big.scales * 0 + 0.1
    with pytest.raises(SceneRefused, match="300 splats have a standard deviation above"):
        check_physical(big, ref, LIM)
    far = synthetic_rope(300, seed=3)
    far.means = far.means + torch.tensor([0.0, 0.0, 30.0])
    with pytest.raises(SceneRefused, match="centre is 30 m from the starting scene's"):
        check_physical(far, ref, LIM)
    wide = synthetic_rope(300, seed=3)
    wide.means = (wide.means - wide.means.mean(0)) * 40 + wide.means.mean(0)
    with pytest.raises(SceneRefused, match="bounding radius .* more than max_extent_ratio"):
        check_physical(wide, ref, LIM)
    nan = synthetic_rope(300, seed=3)
    nan.means[4, 1] = float("nan")
    with pytest.raises(SceneRefused, match="non-finite"):
        check_physical(nan, ref, LIM)
    with pytest.raises(SceneRefused, match="more than max_splats"):
        check_physical(synthetic_rope(60, seed=3), ref, SceneLimits(max_splats=50))


def test_the_path_policy_allows_real_paths_inside_its_folders_only(tmp_path):
    ok_dir, out_dir = tmp_path / "ok", tmp_path / "out"
    ok_dir.mkdir()
    out_dir.mkdir()
    rope = synthetic_rope(200, seed=4)
    write_ply(ok_dir / "a.ply", rope)
    write_splat(ok_dir / "a.splat", rope)
    write_ply(out_dir / "b.ply", rope)
    (ok_dir / "bundle").mkdir()
    write_ply(ok_dir / "bundle" / "splats.ply", rope)
    (ok_dir / "link.ply").symlink_to(out_dir / "b.ply")
    (ok_dir / "inner.ply").symlink_to(ok_dir / "a.ply")
    (ok_dir / "loop.ply").symlink_to(ok_dir / "loop.ply")
    (ok_dir / "notes.txt").write_text("secret")
    os.mkfifo(ok_dir / "fifo.ply")
    pol = ScenePathPolicy([ok_dir, tmp_path / "not_yet"])
    for p in ("a.ply", "a.splat", "bundle", "inner.ply"):
        assert len(read_scene_file(str(ok_dir / p), pol, LIM)) == 200, p
    for p in (out_dir / "b.ply", ok_dir / "link.ply", ok_dir / "loop.ply", ok_dir / "notes.txt", ok_dir / "fifo.ply",
              ok_dir / "missing.ply", ok_dir / ".." / "out" / "b.ply", "/etc/passwd", "/dev/zero", out_dir):
        with pytest.raises(SceneRefused) as err:
            read_scene_file(str(p), pol, LIM)
        assert str(err.value) == GENERIC_REFUSAL, p
    with pytest.raises(SceneRefused, match="must be an absolute path"):
        read_scene_file("ok/a.ply", pol, LIM)
    with pytest.raises(SceneRefused, match=r"a.ply: \d+ bytes, more than max_file_bytes \(100\)"):
        read_scene_file(str(ok_dir / "a.ply"), pol, SceneLimits(max_file_bytes=100))
    with pytest.raises(SceneRefused, match="announces 200 vertices, more than the limit of 10"):
        read_scene_file(str(ok_dir / "a.ply"), pol, SceneLimits(max_splats=10))
    # messages about files inside the folders name the file, never the full resolved path
    with pytest.raises(SceneRefused) as err:
        read_scene_file(str(ok_dir / "a.ply"), pol, SceneLimits(max_splats=10))
    assert str(ok_dir) not in str(err.value)


def test_limits_are_validated():
    with pytest.raises(ValueError, match="max_splats"):
        SceneLimits(max_splats=0)
    with pytest.raises(ValueError, match="max_scale_ratio"):
        SceneLimits(max_scale_ratio=0.0)
    assert SceneExtent.of(synthetic_rope(100)).radius > 0
    assert np.isfinite(SceneExtent.of(synthetic_rope(100)).center).all()
