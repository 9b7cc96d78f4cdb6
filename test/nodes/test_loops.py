"""FixedRateLoop (soma_ros/nodes/loops.py): the live node's physics and output threads."""

from __future__ import annotations

import threading
import time

import pytest

from soma_ros.nodes.loops import FixedRateLoop, StepPhase


def _wait(pred, timeout=10.0):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline and not pred():
        time.sleep(0.005)
    return pred()


def test_loop_calls_and_stops():
    calls = []
    loop = FixedRateLoop("t", 200.0, lambda: calls.append(time.monotonic())).start()
    assert _wait(lambda: len(calls) >= 5)
    assert loop.running
    assert loop.stop()
    n = len(calls)
    time.sleep(0.05)
    assert len(calls) == n  # nothing runs after stop() returned
    assert not loop.running and loop.error is None and loop.ticks == n


def test_overruns_are_skipped_not_run_back_to_back():
    """fn takes ~3 periods: missed ticks are counted and dropped, so calls never pile up
    into a catch-up burst (each call starts after the previous one ended)."""
    period = 0.01
    spans = []

    def slow():
        t0 = time.monotonic()
        time.sleep(3 * period)
        spans.append((t0, time.monotonic()))

    loop = FixedRateLoop("slow", 1.0 / period, slow).start()
    assert _wait(lambda: len(spans) >= 6)
    loop.stop()
    assert loop.overruns >= 5  # at least one skipped tick per call after the first
    assert all(b[0] >= a[1] for a, b in zip(spans, spans[1:]))


def test_an_escaping_exception_stops_the_loop_and_is_kept():
    def boom():
        raise RuntimeError("bad step")

    loop = FixedRateLoop("boom", 100.0, boom).start()
    assert _wait(lambda: loop.error is not None)
    assert isinstance(loop.error, RuntimeError) and not loop.running
    assert loop.stop()


def test_stop_from_inside_the_loop_does_not_deadlock():
    box = {}

    def fn():
        box["stopped"] = box["loop"].stop()

    box["loop"] = FixedRateLoop("self", 100.0, fn)
    box["loop"].start()
    assert _wait(lambda: "stopped" in box)
    assert _wait(lambda: not threading.Thread.is_alive(box["loop"]._thread))


@pytest.mark.parametrize("rate", [0.0, -1.0])
def test_bad_rate_is_refused(rate):
    with pytest.raises(ValueError, match="rate must be > 0"):
        FixedRateLoop("x", rate, lambda: None)


def test_step_phase_starts_other_work_right_after_a_step():
    """A loop that calls after_step() starts its work in the idle part of the physics period:
    after a step ended and before the next one begins."""
    phase = StepPhase()
    windows = []  # (begin, end) of every step

    def step():
        phase.begin()
        t0 = time.monotonic()
        time.sleep(0.005)
        windows.append((t0, time.monotonic()))
        phase.end()

    starts = []

    def other():
        if phase.after_step(timeout=0.1):
            starts.append(time.monotonic())

    physics = FixedRateLoop("physics", 40.0, step).start()
    worker = FixedRateLoop("other", 13.0, other).start()
    assert _wait(lambda: len(starts) >= 6)
    worker.stop()
    physics.stop()
    for s in starts:
        inside = [w for w in windows if w[0] <= s <= w[1]]
        assert not inside, (s, inside)
        assert any(w[1] <= s for w in windows)


def test_step_phase_wait_ends_at_its_timeout_without_steps():
    phase = StepPhase()
    t0 = time.monotonic()
    assert phase.after_step(timeout=0.05) is False
    assert 0.04 <= time.monotonic() - t0 < 1.0
    phase.begin()
    phase.end()
    assert phase.steps_ended == 1
