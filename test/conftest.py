"""Shared pytest fixtures.

Every test that touches ROS gets its own rclpy Context and its own
ROS_DOMAIN_ID with LOCALHOST discovery (the network rule), so tests never see
each other's traffic and nothing leaves loopback.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared"

# Test modules import helpers from each other by module name (``from test_checkpoint import ...``);
# every folder of the suite is on the path, whichever subset runs.
for _folder in sorted(p for p in Path(__file__).resolve().parent.iterdir() if p.is_dir() and p.name != "__pycache__"):
    if str(_folder) not in sys.path:
        sys.path.append(str(_folder))

# Set before anything can import rclpy or torch.
os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("MUJOCO_GL", "egl")

try:
    import torch

    torch.set_num_threads(1)
except ImportError:  # pragma: no cover
    pass


@pytest.fixture
def domain_id() -> int:
    from soma_ros.nodes.testing import unique_domain_id

    return unique_domain_id()


@pytest.fixture
def ros_env(domain_id):
    """Environment for child processes: LOCALHOST discovery and this test's domain."""
    from soma_ros.nodes.testing import ros_env as make_env

    return make_env(domain_id)


@pytest.fixture
def ros_context(domain_id):
    """An initialised rclpy Context on this test's domain, shut down afterwards."""
    import rclpy
    from rclpy.context import Context

    os.environ["ROS_DOMAIN_ID"] = str(domain_id)
    ctx = Context()
    rclpy.init(context=ctx, domain_id=domain_id)
    try:
        yield ctx
    finally:
        if ctx.ok():
            rclpy.shutdown(context=ctx)


@pytest.fixture
def ros_executor(ros_context):
    from rclpy.executors import SingleThreadedExecutor

    ex = SingleThreadedExecutor(context=ros_context)
    try:
        yield ex
    finally:
        ex.shutdown()


@pytest.fixture(scope="session")
def shared_dir() -> Path:
    if not SHARED.is_dir():
        pytest.skip(f"shared data folder not found at {SHARED}")
    return SHARED


@pytest.fixture(scope="session")
def untrained_run(tmp_path_factory):
    """(checkpoint, scene dir) of a random-weight `cpu` model on a 2,000-splat synthetic rope."""
    from soma_ros.core.scenes import write_untrained_run

    return write_untrained_run(tmp_path_factory.mktemp("untrained"), n=2000, width=160, height=120)


def sim_node_args(checkpoint, scene, *extra: str) -> list:
    """--ros-args for soma_sim_node."""
    return ["--ros-args", "-p", f"checkpoint:={checkpoint}", "-p", f"scene:={scene}", *extra]


def recorded_grasp(live, bag: Path):
    """A recorded episode's /joint_states as the live engine's joint vectors, with where its
    gripper closes: (vectors [T] in ``live.required_joints`` order, index of the first pose
    closed by 0.05 of the gripper state, the jaws' centre [T, 3] in the simulation frame)."""
    import numpy as np
    from rosbags.highlevel import AnyReader

    from soma_ros.bagtypes import typestore

    vecs = []
    with AnyReader([Path(bag)], default_typestore=typestore()) as r:
        conns = [c for c in r.connections if c.topic == "/joint_states"]
        for c, _, raw in r.messages(connections=conns):
            m = r.deserialize(raw, c.msgtype)
            idx = {n: i for i, n in enumerate(m.name)}
            vecs.append(np.array([float(m.position[idx[n]]) for n in live.required_joints]))
    grip = [float(live.action(v).gripper) for v in vecs]
    k_close = next(i for i, g in enumerate(grip) if g < grip[0] - 0.05)
    tcp = np.stack([live.action(v).control_points.double().mean(0).numpy() for v in vecs])
    return vecs, k_close, tcp


def train_tiny_run(data: Path, run: Path, episodes: int, frames: int, seed: int = 3) -> None:
    """A tiny rope dataset (`episodes` x `frames`) and a barely trained `tiny` model on it
    (2 iterations: the mechanics of what consumes a run, not its accuracy)."""
    from soma_ros.world import generate_dataset, load_world_config
    from soma_ros.training.config import load_train_config
    from soma_ros.training.train import train

    generate_dataset(load_world_config(), "rope", "tiny", data, episodes=episodes, seed=seed, frames=frames, progress=False)
    cfg = load_train_config("tiny", {
        "scene": {"photometric_iters": 3},
        "schedule": {"iters_per_epoch": 1, "stage1": {"epochs": 1, "stride": 2, "length_start": 2},
                     "stage2": {"epochs": 1, "window": 3}},
        "run": {"val_episodes": 1, "val_frame_stride": 3}})
    train(cfg, data, run, log=lambda *a, **k: None)


#: Fixtures that generate reference-world bags, train a model or run one for minutes: a test
#: that uses one is marked ``slow``; ``make test-fast`` runs the others (``-m "not slow"``).
HEAVY_FIXTURES = {
    "tiny_run", "resim_out", "good_dataset", "clean_run", "bench_run", "trained_run", "two_episodes",
    "world", "reference", "world_bag", "rope_bag", "reference_scene", "guarded", "lift_dataset", "worlds",
    "reports", "bag", "arx_run",
    "ros_env", "ros_context",  # tests that start ROS nodes or processes
}
#: Tests that take more than about 10 s on a 2-core machine without any of those fixtures.
SLOW_TESTS = {
    "test_check_arx5_config", "test_check_broken_urdf",
    "test_a_clamped_rod_droops_as_an_euler_bernoulli_cantilever_and_rests_where_it_lies",
    "test_a_tilting_grip_turns_the_held_section_about_the_closing_axis_as_a_rotational_spring",
    "test_the_live_engine_runs_a_physics_model_exact_at_rest_and_lifts_a_grasped_rope",
    "test_the_newton_solver_makes_a_stiff_rope_stiff_and_its_bending_compliance_matter",
    "test_build_command_is_idempotent", "test_long_rollout_13k_random_weights_is_finite_and_bounded",
    "test_real_capture_holdout", "test_gripper_out_of_reach_moves_nothing_and_through_the_rope_moves_it",
    "test_passive_rule_is_a_live_option_and_stops_the_root_after_a_push",
    "test_settling_makes_a_moved_object_still_again_and_only_with_the_robot_away",
    "test_efforts_feel_a_heavier_rope_but_not_a_softer_one", "test_wind_onset_starts_the_wind_inside_the_carry",
}


def pytest_configure(config):
    config.addinivalue_line("markers", "slow: generates worlds, trains or runs a model for long (not in make test-fast)")


def pytest_collection_modifyitems(config, items):
    for item in items:
        if HEAVY_FIXTURES & set(getattr(item, "fixturenames", ())) or item.originalname in SLOW_TESTS:
            item.add_marker(pytest.mark.slow)
