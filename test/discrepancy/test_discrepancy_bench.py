"""The discrepancy benchmark's scoring arithmetic (benchmarks/discrepancy.py): raw and
effect-attributable (excess over the effect-free floor) shrink of the held-out gap, on hand-made rows."""

from __future__ import annotations

import pytest

from benchmarks.discrepancy import format_table, load_world, order_effects, score_gap

FLOOR = {"rmse": 0.030, "chamfer": 0.020}


def test_excess_shrink_is_relative_to_the_floor():
    # effect raises rmse 0.030 -> 0.050 and chamfer 0.020 -> 0.060; the change removes most of it
    r = score_gap({"rmse": 0.050, "chamfer": 0.060}, {"rmse": 0.035, "chamfer": 0.030}, FLOOR)
    assert r["ratio_rmse"] == pytest.approx(0.7) and r["ratio_chamfer"] == pytest.approx(0.5)
    assert r["excess_before_rmse"] == pytest.approx(0.020) and r["excess_after_rmse"] == pytest.approx(0.005)
    assert r["excess_before_chamfer"] == pytest.approx(0.040) and r["excess_after_chamfer"] == pytest.approx(0.010)
    assert r["ratio_excess_rmse"] == pytest.approx(0.25) and r["ratio_excess_chamfer"] == pytest.approx(0.25)
    assert r["floor_rmse"] == 0.030 and r["floor_chamfer"] == 0.020
    assert r["halved_excess"] is True
    assert r["halved_raw"] is False  # 0.7 on rmse: the floor keeps the raw gap from halving


def test_excess_not_halved_when_only_one_metric_shrinks_and_can_go_below_floor():
    r = score_gap({"rmse": 0.050, "chamfer": 0.060}, {"rmse": 0.025, "chamfer": 0.045}, FLOOR)
    assert r["ratio_excess_rmse"] == pytest.approx(-0.25)  # after below the floor: negative excess, counts as halved
    assert r["ratio_excess_chamfer"] == pytest.approx(0.625)
    assert r["halved_excess"] is False
    assert r["halved_raw"] is False


def test_no_excess_or_no_floor_gives_undefined_ratios():
    # the effect does not raise the metric above the floor (e.g. the negative control itself)
    r = score_gap(dict(FLOOR), dict(FLOOR), FLOOR)
    assert r["excess_before_rmse"] == 0.0 and r["ratio_excess_rmse"] is None and r["halved_excess"] is None
    assert r["ratio_rmse"] == pytest.approx(1.0) and r["halved_raw"] is False
    r = score_gap({"rmse": 0.025, "chamfer": 0.03}, {"rmse": 0.02, "chamfer": 0.01}, FLOOR)
    assert r["excess_before_rmse"] == pytest.approx(-0.005) and r["ratio_excess_rmse"] is None
    assert r["halved_excess"] is None
    # no floor (benchmark run without the negative control)
    r = score_gap({"rmse": 0.05, "chamfer": 0.06}, {"rmse": 0.02, "chamfer": 0.02}, None)
    assert r["excess_before_rmse"] is None and r["ratio_excess_chamfer"] is None and r["halved_excess"] is None
    assert r["halved_raw"] is True
    # a missing metric
    r = score_gap({"rmse": 0.05}, {"rmse": 0.02}, FLOOR)
    assert r["ratio_chamfer"] is None and r["halved_raw"] is None and r["halved_excess"] is None


def test_negative_control_runs_first_and_table_names_both_definitions():
    assert order_effects(["wind", "slip", "none"]) == ["none", "wind", "slip"]
    assert order_effects(["wind", "slip"]) == ["wind", "slip"]
    rank = [{"name": "wind", "explained_fraction": 0.6, "uncertainty": 0.1},
            {"name": "mass_scale", "explained_fraction": 0.1, "uncertainty": 0.05}]
    rows = []
    for hidden, named, gb, ga, floor in ((["none"], "none", FLOOR, FLOOR, FLOOR),
                                         (["wind"], "wind", {"rmse": 0.05, "chamfer": 0.06},
                                          {"rmse": 0.035, "chamfer": 0.03}, FLOOR)):
        det = ({"assessed": True, "detected": True, "auc": 0.8, "auc_low": 0.62} if named == "wind"
               else {"assessed": False, "detected": None})
        rows.append({"hidden": hidden, "named": named, "match": True, "ranking": rank, "gap_before": gb,
                     "gap_after": ga, "detection": det, **score_gap(gb, ga, floor)})
    lines = format_table(rows, "# t")
    head = next(ln for ln in lines if ln.startswith("| hidden"))
    assert "halved (raw)" in head and "halved (excess)" in head
    body = [ln for ln in lines if ln.startswith("| none") or ln.startswith("| wind")]
    assert len(body) == 2 and all(ln.count("|") == head.count("|") for ln in body)
    assert body[0].rstrip().endswith("| n/a |")  # the control has no excess to halve
    assert "0.25 / 0.25 | yes |" in body[1] and "0.70 / 0.50 | no |" in body[1]
    assert "| yes (0.80, 0.62) |" in body[1] and "| none | none | yes | n/a |" in body[0]
    # with the wrist load the winner is the best score, not the best 3D fraction: both are shown
    loaded = [{"name": "mass_scale", "explained_fraction": 0.369, "uncertainty": 0.056, "load_explained": 0.293,
               "score": 0.662},
              {"name": "stiffness_scale", "explained_fraction": 0.416, "uncertainty": 0.04, "load_explained": -0.003,
               "score": 0.413}]
    line = format_table([{**rows[1], "hidden": ["heavy"], "named": "mass_scale", "ranking": loaded}], "# t")[-1]
    assert "| mass_scale +0.369±0.056 + load +0.293 = +0.662 | stiffness_scale +0.416 + load -0.003 = +0.413 |" in line


def test_effects_config_replaces_only_the_magnitudes():
    base, strong = load_world(), load_world(effects_config="effects_discrepancy")
    assert base.effects.wind.velocity == [0.0, 6.0, 0.0] and strong.effects.wind.velocity == [0.0, 8.5, 0.0]
    assert strong.effects.table_friction.friction == 0.03
    assert strong.table == base.table and strong.objects == base.objects and strong.physics == base.physics
    with pytest.raises(FileNotFoundError, match="no_such_effects"):
        load_world(effects_config="no_such_effects")


def test_frames_sets_the_generated_episode_length_and_refuses_reused_data_of_another(tmp_path, capsys):
    """--frames N: the tiny preset's episodes are N frames (the same motions, slower); data already in
    OUT of another length is refused with a clear error, not silently reused."""
    import json

    from benchmarks.discrepancy import _generate, main

    cfg = load_world(frames=80)
    assert cfg.presets["tiny"].frames == [80, 80] and load_world().presets["tiny"].frames == [40, 40]
    assert cfg.presets["paper"].frames == load_world().presets["paper"].frames
    with pytest.raises(ValueError, match="at least 2"):
        load_world(frames=1)
    data = tmp_path / "data" / "rope_none"
    data.mkdir(parents=True)
    (data / "manifest.json").write_text(json.dumps({"episodes": [{"name": "rope_000", "frames": 40}]}))
    assert _generate("rope", data, 1, 0, "none", None, lambda *a: None, None, 40) == data  # same length: reused
    with pytest.raises(ValueError, match=r"\[40\] frames, not 80"):
        _generate("rope", data, 1, 0, "none", None, lambda *a: None, None, 80)
    # the CLI says what is wrong in one line (here: a --run folder without a checkpoint), no traceback
    assert main(["--object", "rope", "--effects", "none", "--no-negative", "--frames", "80",
                 "--out", str(tmp_path), "--run", str(tmp_path / "no_run")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("benchmarks.discrepancy: error:") and "no_run" in err
