"""stop_process_group: a child and the helpers it started are all gone afterwards."""

import os
import signal
import subprocess
import sys
import time

from soma_ros.core.processes import stop_process_group

# A leader that starts a helper ignoring SIGTERM (as a browser's or a node's helpers may), prints
# the helper's pid and waits; the leader itself exits on SIGTERM.
_LEADER = """
import subprocess, sys, time
helper = subprocess.Popen([sys.executable, "-c",
    "import signal, time; signal.signal(signal.SIGTERM, signal.SIG_IGN); print('up', flush=True); time.sleep(600)"],
    stdout=subprocess.PIPE, text=True)
assert helper.stdout.readline().strip() == "up"
print(helper.pid, flush=True)
time.sleep(600)
"""


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    with open(f"/proc/{pid}/stat") as f:  # a zombie (exited, not yet reaped by its parent) is gone
        return f.read().rsplit(")", 1)[1].split()[0] != "Z"


def test_a_helper_that_ignores_sigterm_is_killed_with_its_group():
    proc = subprocess.Popen([sys.executable, "-c", _LEADER], stdout=subprocess.PIPE, text=True, process_group=0)
    helper = int(proc.stdout.readline())
    assert _alive(helper)
    stop_process_group(proc, (signal.SIGTERM, signal.SIGKILL), timeout_s=1.0)
    assert proc.returncode == -signal.SIGTERM  # the leader went at the first signal
    deadline = time.monotonic() + 5.0
    while _alive(helper) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not _alive(helper)  # the helper survived SIGTERM and went at SIGKILL
    proc.stdout.close()


def test_a_process_that_has_exited_is_reaped_without_error():
    proc = subprocess.Popen([sys.executable, "-c", "pass"], process_group=0)
    while proc.poll() is None:
        time.sleep(0.01)
    stop_process_group(proc, timeout_s=0.5)
    assert proc.returncode == 0
