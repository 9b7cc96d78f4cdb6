"""Evaluation scoring against hand-computed cases: Chamfer, the table-completed depth maps,
per-frame masking of image metrics, per-episode / per-split aggregation, and the
evaluation-only ground-truth reader."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from soma_ros.core.cameras import Cameras, look_at
from soma_ros.core.scoring import (
    FrameScores,
    aggregate_episodes,
    aggregate_frames,
    chamfer_distance,
    complete_depth_maps,
    depth_error_shares,
    score_frame,
    table_depth,
)

torch.set_num_threads(1)


# ------------------------------------------------------------------ Chamfer
def test_chamfer_hand_computed():
    a = torch.tensor([[0.0, 0.0, 0.0]])
    b = torch.tensor([[1.0, 0.0, 0.0], [3.0, 0.0, 0.0]])
    # a -> b: 1; b -> a: (1 + 3) / 2 = 2; symmetric mean: 1.5
    assert chamfer_distance(a, b) == pytest.approx(1.5)
    assert chamfer_distance(b, a) == pytest.approx(1.5)
    # identical sets: 0; a grid shifted by 1 mm (spacing 1 cm): 1 mm both ways
    g = torch.stack(torch.meshgrid(*[torch.arange(5.0) * 0.01] * 3, indexing="ij"), -1).reshape(-1, 3)
    assert chamfer_distance(g, g) == 0.0
    assert chamfer_distance(g, g + torch.tensor([0.0, 0.0, 0.001])) == pytest.approx(0.001, rel=1e-5)  # float32 input
    # chunking does not change the value
    r = torch.rand(300, 3, generator=torch.Generator().manual_seed(0))
    s = torch.rand(200, 3, generator=torch.Generator().manual_seed(1))
    assert chamfer_distance(r, s, chunk=7) == pytest.approx(chamfer_distance(r, s), rel=1e-12)
    with pytest.raises(ValueError, match="empty"):
        chamfer_distance(torch.zeros(0, 3), s)
    with pytest.raises(ValueError, match=r"\[N, 3\]"):
        chamfer_distance(torch.zeros(4, 2), s)


# ------------------------------------------------------------------ table depth
def _down_camera(height: float, W: int = 8, H: int = 6, f: float = 10.0) -> Cameras:
    K = torch.tensor([[f, 0.0, W / 2], [0.0, f, H / 2], [0.0, 0.0, 1.0]], dtype=torch.float64)
    pose = look_at((0.0, 0.0, height), (0.0, 0.0, 0.0), up=(0.0, 1.0, 0.0))
    return Cameras.from_cam_to_world(K[None], pose[None], W, H, ["down"])


def test_table_depth_analytic():
    cam = _down_camera(1.25)
    d = table_depth(cam, torch.tensor([0.0, 0.0, 1.0]), 0.0)
    # looking straight down on z = 0 from 1.25 m: camera-z depth 1.25 at every pixel
    torch.testing.assert_close(d, torch.full((1, 6, 8), 1.25))
    # a table at z = 0.25 (n.x + d = 0 with d = -0.25): depth 1.0
    torch.testing.assert_close(table_depth(cam, torch.tensor([0.0, 0.0, 1.0]), -0.25), torch.full((1, 6, 8), 1.0))
    # a camera looking up (away from the plane) never hits it: 0
    pose = look_at((0.0, 0.0, 1.0), (0.0, 0.0, 2.0), up=(0.0, 1.0, 0.0))
    up_cam = Cameras.from_cam_to_world(cam.K, pose[None], 8, 6)
    assert table_depth(up_cam, torch.tensor([0.0, 0.0, 1.0]), 0.0).abs().max() == 0
    # a camera tilted by 45 deg about x, 1 m above the table: centre ray hits at range sqrt(2), camera z = sqrt(2)
    pose = look_at((0.0, -1.0, 1.0), (0.0, 0.0, 0.0), up=(0.0, 0.0, 1.0))
    K = torch.tensor([[10.0, 0.0, 1.0], [0.0, 10.0, 1.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    tilt = Cameras.from_cam_to_world(K[None], pose[None], 2, 2)
    d = table_depth(tilt, torch.tensor([0.0, 0.0, 1.0]), 0.0)[0]
    # pixel centres (0.5, 0.5)...(1.5, 1.5) are +-0.05 rad off-axis: rows differ, the mean is ~sqrt(2)
    assert float(d.mean()) == pytest.approx(math.sqrt(2.0), rel=5e-3)
    assert float(d[1].mean()) < float(d[0].mean())  # lower image rows look nearer


# ------------------------------------------------------------------ depth completion
def test_complete_depth_maps_paper_rule():
    C, H, W = 1, 4, 5
    table = torch.full((C, H, W), 1.5)
    gt = torch.full((C, H, W), 1.5)  # measured: table everywhere ...
    obj = torch.zeros(C, H, W, dtype=torch.bool)
    obj[0, 1:3, 1:3] = True  # ... and a 2x2 object at 1.0 m
    gt[obj] = 1.0
    # (a) the prediction renders the object 10 cm too far on exactly its pixels
    pd = torch.zeros(C, H, W)
    alpha = torch.zeros(C, H, W)
    pd[obj], alpha[obj] = 1.1, 1.0
    p, g, region = complete_depth_maps(pd, alpha, gt, obj, None, table)
    assert torch.equal(region, obj)
    torch.testing.assert_close(p[obj], torch.full((4,), 1.1))
    torch.testing.assert_close(p[~obj], torch.full((16,), 1.5))  # empty pixels read as table
    # (b) nothing rendered: the object pixels read as table (1.5 m) instead of 0
    p, g, region = complete_depth_maps(torch.zeros(C, H, W), torch.zeros(C, H, W), gt, obj, None, table)
    torch.testing.assert_close(p[obj], torch.full((4,), 1.5))
    # (c) half transparent: D + (1 - alpha) table
    p, _, _ = complete_depth_maps(torch.full((C, H, W), 1.0), torch.full((C, H, W), 0.5), gt, obj, None, table)
    torch.testing.assert_close(p, torch.full((C, H, W), 1.25))
    # (d) rendered in the wrong place: region is the union; robot pixels and rays off the table leave it
    pd2, a2 = torch.zeros(C, H, W), torch.zeros(C, H, W)
    pd2[0, 0, 3:5], a2[0, 0, 3:5] = 1.2, 1.0
    robot = torch.zeros(C, H, W, dtype=torch.bool)
    robot[0, 1, 1] = True
    table2 = table.clone()
    table2[0, 0, 4] = 0.0
    _, g, region = complete_depth_maps(pd2, a2, gt, obj, robot, table2)
    expect = obj.clone()
    expect[0, 0, 3] = True
    expect[0, 1, 1] = False
    assert torch.equal(region, expect)
    assert float(g[0, 0, 3]) == 1.5  # ground truth there is the table
    # (e) the evaluation's region: the measured object only, minus robot pixels (and rays off the table)
    _, _, region = complete_depth_maps(pd2, a2, gt, obj, robot, table2, region="measured")
    expect = obj.clone()
    expect[0, 1, 1] = False
    assert torch.equal(region, expect)
    with pytest.raises(ValueError, match="region"):
        complete_depth_maps(pd2, a2, gt, obj, robot, table2, region="everything")


def _frame_inputs():
    C, H, W = 2, 32, 40
    obj = torch.zeros(C, H, W, dtype=torch.bool)
    obj[:, 8:24, 10:30] = True
    gen = torch.Generator().manual_seed(5)
    gt_rgb = torch.rand(C, H, W, 3, generator=gen) * 0.6 + 0.2
    gt_depth = torch.full((C, H, W), 1.5)
    gt_depth[obj] = 1.0
    table = torch.full((C, H, W), 1.5)
    return C, H, W, obj, gt_rgb, gt_depth, table


def test_score_frame_masks_and_values():
    C, H, W, obj, gt_rgb, gt_depth, table = _frame_inputs()
    sign = torch.where(torch.arange(H * W * 3).reshape(H, W, 3) % 2 == 0, 1.0, -1.0)
    # prediction: the object's true colours +-0.1 on the object, garbage off the object where the
    # ground truth is masked out -> counts (the prediction is not masked by the object mask)
    pred = gt_rgb * obj[..., None] + 0.1 * sign * obj[..., None]
    robot = torch.zeros(C, H, W, dtype=torch.bool)
    robot[1, 0:8, :] = True  # camera 1: the robot covers rows 0-7 ...
    pred[1, 0:8] = 0.9  # ... where the prediction shows something: ignored (black in both)
    pd = torch.zeros(C, H, W)
    alpha = torch.zeros(C, H, W)
    pd[obj], alpha[obj] = 1.2, 1.0  # 20 cm too far: AbsRel 0.2, RMSE 0.2
    s = score_frame(3, pred, pd, alpha, gt_rgb, gt_depth, obj, robot, table, ["a", "b"])
    # MSE = 0.01 on the object's 16 x 20 pixels of 32 x 40 -> 0.01 * 320 / 1280 = 0.0025 -> 26.02 dB
    expect_psnr = 10 * math.log10(1 / (0.01 * 320 / 1280))
    for cam in ("a", "b"):
        assert s.per_camera[cam]["psnr"] == pytest.approx(expect_psnr, abs=1e-3)
        assert s.per_camera[cam]["abs_rel"] == pytest.approx(0.2, rel=1e-5)
        assert s.per_camera[cam]["rmse"] == pytest.approx(0.2, rel=1e-5)
        assert 0 < s.per_camera[cam]["ssim"] < 1 and s.per_camera[cam]["lpips"] > 0
        assert s.per_camera[cam]["depth_pixels"] == 320
    assert math.isnan(s.chamfer)
    # per camera, exactly the core protocol (soma_ros.core.metrics.image_metrics)
    from soma_ros.core import metrics as M

    for c, cam in enumerate(("a", "b")):
        im = M.image_metrics(pred[c], gt_rgb[c], obj[c], robot[c])
        assert s.per_camera[cam]["psnr"] == pytest.approx(im["psnr"], rel=1e-6)
        assert s.per_camera[cam]["ssim"] == pytest.approx(im["ssim"], rel=1e-6)
        assert s.per_camera[cam]["lpips"] == pytest.approx(im["lpips"], rel=1e-5)
    # without the robot mask camera 1's occluded garbage counts
    s2 = score_frame(3, pred, pd, alpha, gt_rgb, gt_depth, obj, None, table, ["a", "b"])
    assert s2.per_camera["b"]["psnr"] < expect_psnr - 3
    # the object rendered one object-width to the right: depth error on both footprints
    pd3, a3 = torch.zeros(C, H, W), torch.zeros(C, H, W)
    pd3[:, 8:24, 30:40], a3[:, 8:24, 30:40] = 1.0, 1.0
    s3 = score_frame(3, pred, pd3, a3, gt_rgb, gt_depth, obj, None, table, ["a", "b"],
                     pred_points=torch.zeros(1, 3), gt_points=torch.tensor([[0.0, 0.0, 0.5]]))
    # scored region: the 320 measured pixels (pred table 1.5 vs gt 1.0: |0.5|)
    assert s3.per_camera["a"]["depth_pixels"] == 320
    assert s3.per_camera["a"]["rmse"] == pytest.approx(0.5, rel=1e-5)
    assert s3.per_camera["a"]["abs_rel"] == pytest.approx(0.5, rel=1e-5)
    # union: + 160 predicted pixels (1.0 vs table 1.5: 0.5)
    assert s3.per_camera["a"]["depth_pixels_union"] == 480
    assert s3.per_camera["a"]["rmse_union"] == pytest.approx(0.5, rel=1e-5)
    assert s3.per_camera["a"]["abs_rel_union"] == pytest.approx((320 * 0.5 / 1.0 + 160 * 0.5 / 1.5) / 480, rel=1e-5)
    # an object rendered on its own pixels but also 1 cm above the table off them (say, where it lay
    # before): the measured region is unchanged, the union dilutes: sqrt(320 * 0.2^2 / 480 + 160 * 0.01^2 / 480)
    pd4, a4 = pd.clone(), alpha.clone()
    pd4[:, 8:24, 30:40], a4[:, 8:24, 30:40] = 1.49, 1.0
    s4 = score_frame(3, pred, pd4, a4, gt_rgb, gt_depth, obj, None, table, ["a", "b"])
    assert s4.per_camera["a"]["rmse"] == pytest.approx(0.2, rel=1e-5)
    assert s4.per_camera["a"]["rmse_union"] == pytest.approx(math.sqrt((320 * 0.04 + 160 * 1e-4) / 480), rel=1e-4)
    assert s3.chamfer == pytest.approx(0.5)
    with pytest.raises(ValueError, match="camera names"):
        score_frame(3, pred, pd, alpha, gt_rgb, gt_depth, obj, robot, table, ["a"])


def test_depth_error_breakdown_by_rendered_coverage():
    """The measured object's 320 pixels: the left half rendered solid 10 cm too far (covered), the
    next 4 columns at alpha 0.3 on the true depth (edge: 0.7 of the table's 0.5 m gap), the last 6
    columns empty (missed: the table, 0.5 m behind). Counts, sums, shares and RMS per class."""
    C, H, W, obj, gt_rgb, gt_depth, table = _frame_inputs()
    pd, alpha = torch.zeros(C, H, W), torch.zeros(C, H, W)
    pd[:, 8:24, 10:20], alpha[:, 8:24, 10:20] = 1.1, 1.0
    pd[:, 8:24, 20:24], alpha[:, 8:24, 20:24] = 1.0, 0.3
    s = score_frame(1, gt_rgb, pd, alpha, gt_rgb, gt_depth, obj, None, table, ["a", "b"])
    row = s.per_camera["a"]
    assert (row["depth_px_covered"], row["depth_px_edge"], row["depth_px_missed"]) == (160, 64, 96)
    assert row["depth_sq_covered"] == pytest.approx(160 * 0.1 ** 2, rel=1e-4)
    assert row["depth_sq_edge"] == pytest.approx(64 * 0.35 ** 2, rel=1e-4)
    assert row["depth_sq_missed"] == pytest.approx(96 * 0.5 ** 2, rel=1e-4)
    total = sum(row[f"depth_sq_{c}"] for c in ("covered", "edge", "missed"))
    assert row["rmse"] == pytest.approx(math.sqrt(total / 320), rel=1e-4)
    shares = depth_error_shares(aggregate_frames([s]))
    assert shares["missed"]["pixels"] == pytest.approx(0.3) and shares["edge"]["rms"] == pytest.approx(0.35, rel=1e-4)
    assert sum(v["error"] for v in shares.values()) == pytest.approx(1.0)
    assert shares["missed"]["error"] == pytest.approx(96 * 0.25 / total, rel=1e-4)
    assert depth_error_shares({"rmse": 0.1}) == {}


def test_aggregation_over_frames_and_episodes():
    def fs(frame, psnr_a, psnr_b, rmse, chamfer):
        f = FrameScores(frame=frame, chamfer=chamfer)
        for cam, p in (("a", psnr_a), ("b", psnr_b)):
            f.per_camera[cam] = {"psnr": p, "ssim": 0.5, "lpips": 0.1, "abs_rel": rmse / 2, "rmse": rmse,
                                 "rmse_union": 2 * rmse}
        return f

    frames = [fs(1, 20.0, 30.0, 0.1, 0.01), fs(2, 10.0, math.inf, 0.3, 0.03), fs(3, 40.0, 20.0, math.nan, 0.02)]
    e = aggregate_frames(frames)
    # PSNR: the inf image (both black) is left out: (20 + 30 + 10 + 40 + 20) / 5
    assert e["psnr"] == pytest.approx(24.0)
    assert e["n_infinite_psnr"] == 1 and e["n_undefined"]["psnr"] == 1
    # RMSE: NaN images (empty region) left out: (0.1 + 0.1 + 0.3 + 0.3) / 4
    assert e["rmse"] == pytest.approx(0.2) and e["n_undefined"]["rmse"] == 2
    assert e["chamfer"] == pytest.approx(0.02)
    assert e["rmse_union"] == pytest.approx(0.4)  # the extra metrics aggregate the same way
    assert e["per_camera"]["a"]["psnr"] == pytest.approx(70 / 3)
    assert e["frames"] == 3
    # split: mean of the episode means (not of the frames)
    split = aggregate_episodes({"e1": e, "e2": {"psnr": 30.0, "rmse": 0.4, "chamfer": math.nan}})
    assert split["psnr"] == pytest.approx(27.0)
    assert split["rmse"] == pytest.approx(0.3)
    assert split["chamfer"] == pytest.approx(0.02)  # NaN episode left out
    assert split["episodes"] == 2
    with pytest.raises(ValueError):
        aggregate_frames([])


# ------------------------------------------------------------------ ground truth reader
def _write_gt_bag(path, clouds, cloud_stamps, image_stamps):
    from rosbags.rosbag2 import Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_JAZZY)
    T = ts.types

    def header(ns, frame):
        return T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9),
                                        frame_id=frame)

    fields = [T["sensor_msgs/msg/PointField"](name=n, offset=4 * i, datatype=7, count=1) for i, n in enumerate("xyz")]
    with Writer(path, version=9) as w:
        cpc = w.add_connection("/world/object_points", "sensor_msgs/msg/PointCloud2", typestore=ts)
        cim = w.add_connection("/cam_a/color/image_raw", "sensor_msgs/msg/Image", typestore=ts)
        for ns, pts in zip(cloud_stamps, clouds):
            p = np.ascontiguousarray(pts, dtype="<f4")
            msg = T["sensor_msgs/msg/PointCloud2"](header=header(ns, "world"), height=1, width=len(p), fields=fields,
                                                   is_bigendian=False, point_step=12, row_step=12 * len(p),
                                                   data=p.view(np.uint8).reshape(-1), is_dense=True)
            w.write(cpc, ns, ts.serialize_cdr(msg, cpc.msgtype))
        for ns in image_stamps:
            msg = T["sensor_msgs/msg/Image"](header=header(ns, "cam_a"), height=1, width=1, encoding="rgb8",
                                             is_bigendian=0, step=3, data=np.zeros(3, np.uint8))
            w.write(cim, ns, ts.serialize_cdr(msg, cim.msgtype))


def test_read_ground_truth_points(tmp_path):
    from soma_ros.evaluation.ground_truth import GroundTruthError, read_ground_truth_points

    t0 = 1_700_000_000 * 10**9
    period = 33_333_333
    clouds = [np.array([[i, 0.0, 0.0], [0.0, i, 1.0]], np.float32) for i in range(5)]
    # clouds 1 ms after each frame; frames on the image clock
    cloud_stamps = [t0 + i * period + 1_000_000 for i in range(5)]
    img_stamps = [t0 + i * period for i in range(5)]
    bag = tmp_path / "ep"
    _write_gt_bag(bag, clouds, cloud_stamps, img_stamps)
    pts = read_ground_truth_points(bag)
    assert pts.shape == (5, 2, 3) and pts.dtype == np.float32
    np.testing.assert_array_equal(pts[3], clouds[3])
    # an explicit clock (every other frame) picks the nearest clouds
    pts2 = read_ground_truth_points(bag, stamps_ns=img_stamps[::2])
    np.testing.assert_array_equal(pts2[:, 0, 0], [0.0, 2.0, 4.0])
    # a frame with no cloud within the tolerance is an error
    with pytest.raises(GroundTruthError, match="within"):
        read_ground_truth_points(bag, stamps_ns=[t0 + 10 * period])
    # a bag without ground truth (a real recording)
    bag2 = tmp_path / "real"
    from rosbags.rosbag2 import Writer

    from rosbags.typesys import Stores, get_typestore

    with Writer(bag2, version=9) as w:
        w.add_connection("/joint_states", "sensor_msgs/msg/JointState", typestore=get_typestore(Stores.ROS2_JAZZY))
    with pytest.raises(GroundTruthError, match="no /world/object_points"):
        read_ground_truth_points(bag2)


def test_training_reader_never_reads_ground_truth():
    """The evaluation-only reader is the only module that names the topic outside the forbidden list."""
    import inspect

    import soma_ros.data.bags as bags
    import soma_ros.data.dataset as dataset

    assert "/world/object_points" in bags.FORBIDDEN_TOPICS
    assert "evaluate_gt" not in inspect.getsource(dataset) and "evaluate_gt" not in inspect.getsource(bags)


def test_comparison_tiles_show_what_is_scored():
    from soma_ros.evaluation.viz import comparison_tiles, sample_frames

    H, W = 6, 8
    gt = torch.full((H, W, 3), 0.5)
    obj = torch.zeros(H, W, dtype=torch.bool)
    obj[2:4, 2:6] = True
    robot = torch.zeros(H, W, dtype=torch.bool)
    robot[0, :] = True
    pred = gt * obj[..., None]
    pred[0, :] = 1.0  # under the robot: blacked out in the simulated tile, no error
    pred[5, 7] = 1.0  # a stray splat off the object: error
    meas, sim, err = comparison_tiles(gt, obj, robot, pred, error_max=0.5)
    assert meas.shape == (H, W, 3) and meas.dtype == np.uint8
    assert (meas[2, 2] == 128).all() and (meas[0, 0] == 0).all() and (meas[5, 5] == 0).all()
    assert (sim[0] == 0).all() and (sim[5, 7] == 255).all()
    # the heat map: the colour of zero error everywhere but at the stray splat (error 1 >= error_max: brightest)
    zero = err[2, 2]
    assert all((err[i, j] == zero).all() for i in range(H) for j in range(W) if (i, j) != (5, 7))
    assert int(err[5, 7].astype(int).sum()) > int(zero.astype(int).sum()) + 300
    assert sample_frames(list(range(1, 40)), 5) == [1, 11, 20, 29, 39]  # linspace(0, 38, 5), rounded
    assert sample_frames([3], 5) == [3] and sample_frames([], 2) == []
