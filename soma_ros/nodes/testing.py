"""Helpers for topic-level tests and benchmarks with real ROS 2 processes.

- :func:`ros_env` builds an environment for child processes with LOCALHOST
  discovery and a given ROS_DOMAIN_ID (the network rule: nothing leaves loopback).
- :func:`unique_domain_id` picks a domain id unlikely to collide with other
  runs on the same machine.
- :class:`RosProcess` starts a console entry point as its own OS process and
  always stops it (SIGINT, then SIGKILL), keeping its output for diagnostics.
- :func:`spin_until` spins an executor until a predicate holds or a deadline
  passes -- no bare sleeps.
"""

from __future__ import annotations

import itertools
import os
import random
import signal
import subprocess
import sys
import tempfile
import time
from typing import Callable, Optional, Sequence

from ..core.processes import stop_process_group

_counter = itertools.count()


def unique_domain_id() -> int:
    """A ROS_DOMAIN_ID in [1, 200] derived from the pid, a counter and randomness."""
    rng = random.Random(os.getpid() * 7919 + next(_counter) * 104729 + time.time_ns())
    return rng.randint(1, 200)


def ros_env(domain_id: int, extra: Optional[dict] = None) -> dict:
    env = dict(os.environ)
    env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    env["ROS_DOMAIN_ID"] = str(domain_id)
    env.pop("ROS_STATIC_PEERS", None)
    env.setdefault("PYTHONUNBUFFERED", "1")
    env.setdefault("OMP_NUM_THREADS", "1")
    if extra:
        env.update(extra)
    return env


class RosProcess:
    """A child process running a soma entry point (``python -m module args``)."""

    def __init__(self, module: str, args: Sequence[str], env: dict, name: str = "") -> None:
        self.name = name or module
        self.log = tempfile.NamedTemporaryFile(prefix=f"soma_{self.name.replace('/', '_')}_", suffix=".log", delete=False)
        self.proc = subprocess.Popen(
            [sys.executable, "-m", module, *args], env=env, stdout=self.log, stderr=subprocess.STDOUT,
            process_group=0,
        )

    def output(self) -> str:
        if not self.log.closed:
            self.log.flush()
        with open(self.log.name, errors="replace") as f:
            return f.read()

    def alive(self) -> bool:
        return self.proc.poll() is None

    def wait(self, timeout: float) -> int:
        return self.proc.wait(timeout=timeout)

    def stop(self, timeout: float = 10.0) -> Optional[int]:
        """SIGINT to the process and its group (a node's clean shutdown), SIGKILL after ``timeout``
        seconds; returns the exit code."""
        if self.proc.poll() is None:
            stop_process_group(self.proc, (signal.SIGINT, signal.SIGKILL), timeout)
        self.log.close()
        return self.proc.returncode

    def __enter__(self) -> "RosProcess":
        return self

    def __exit__(self, *exc) -> None:
        self.stop()


def spin_until(executor, predicate: Callable[[], bool], timeout: float, step: float = 0.05) -> bool:
    """Spin `executor` until predicate() is true or `timeout` seconds pass; returns predicate()."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        executor.spin_once(timeout_sec=step)
    return predicate()


def cloud_variant(base, **changes):
    """A copy of the PointCloud2 ``base`` with some of its fields replaced: the malformed
    scenes that tests and the fuzz benchmark send to ``/soma/reset``."""
    from sensor_msgs.msg import PointCloud2

    cloud = PointCloud2(header=base.header, height=base.height, width=base.width, fields=list(base.fields),
                        is_bigendian=base.is_bigendian, point_step=base.point_step, row_step=base.row_step,
                        data=bytes(base.data), is_dense=base.is_dense)
    for name, value in changes.items():
        setattr(cloud, name, value)
    return cloud
