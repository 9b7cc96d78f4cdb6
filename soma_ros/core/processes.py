"""Stopping a child process together with the helpers it started (its own process group)."""

from __future__ import annotations

import os
import signal
import subprocess
import time
from typing import Sequence

__all__ = ["stop_process_group"]


def stop_process_group(proc: subprocess.Popen, signals: Sequence[int] = (signal.SIGTERM, signal.SIGKILL),
                       timeout_s: float = 10.0) -> None:
    """Stop ``proc``, started as the leader of its own process group (``process_group=0``), and
    every process left in that group: each signal of ``signals`` in turn goes to the whole group,
    and the next one follows when the leader has not exited within ``timeout_s`` or a member of the
    group is still alive ``timeout_s`` after it did. Returns once the group is gone or the last
    signal has had its time. A process that has already exited is reaped; nothing is raised for a
    group that is gone."""
    for sig in signals:
        try:
            os.killpg(proc.pid, sig)
        except (ProcessLookupError, PermissionError):
            pass
        try:
            proc.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            continue
        deadline = time.monotonic() + timeout_s  # the leader is gone: wait for the rest of its group
        while time.monotonic() < deadline:
            try:
                os.killpg(proc.pid, 0)
            except (ProcessLookupError, PermissionError):
                return
            time.sleep(0.05)
