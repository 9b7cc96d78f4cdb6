"""Fixed-rate worker threads for the live node.

The simulator node steps physics and renders in their own threads instead of in
executor timer callbacks: the executor thread then only moves messages in and out
(/joint_states, the reset service), so a burst of input never waits behind a step
or a render, and the executor's per-callback overhead is not paid 30+ times a
second by the physics loop (measured with py-spy on the previous design: 44 % of
the node's time in rclpy's MultiThreadedExecutor loop).

No rclpy here: the loops are plain threads and tested without ROS.
"""

from __future__ import annotations

import threading
import time
from typing import Callable, Optional


class FixedRateLoop:
    """Call ``fn()`` every ``1/rate_hz`` seconds in a daemon thread until :meth:`stop`.

    Ticks are scheduled on an absolute grid (``t0 + k/rate``), so the rate does not
    drift with the time ``fn`` takes. When ``fn`` overruns, the missed ticks are
    skipped (counted in :attr:`overruns`), never run back to back: a live
    simulation that falls behind runs at the rate it can, not in catch-up bursts.
    ``fn`` must handle its own exceptions; one that escapes is stored in
    :attr:`error` and stops the loop.
    """

    def __init__(self, name: str, rate_hz: float, fn: Callable[[], None]) -> None:
        if not rate_hz > 0:
            raise ValueError(f"{name}: rate must be > 0 Hz, got {rate_hz}")
        self.name = name
        self.period = 1.0 / float(rate_hz)
        self.fn = fn
        self.ticks = 0
        self.overruns = 0
        self.error: Optional[BaseException] = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)

    def start(self) -> "FixedRateLoop":
        self._thread.start()
        return self

    def request_stop(self) -> None:
        """Ask the loop to end after its current call, without waiting."""
        self._stop.set()

    def stop(self, timeout: float = 5.0) -> bool:
        """Ask the loop to end and wait for it; returns True if the thread ended."""
        self._stop.set()
        if self._thread.is_alive() and threading.current_thread() is not self._thread:
            self._thread.join(timeout)
        return not self._thread.is_alive()

    @property
    def running(self) -> bool:
        return self._thread.is_alive() and not self._stop.is_set()

    def _run(self) -> None:
        next_t = time.monotonic()
        while not self._stop.is_set():
            try:
                self.fn()
            except BaseException as exc:  # noqa: BLE001 - reported through .error
                self.error = exc
                return
            self.ticks += 1
            next_t += self.period
            now = time.monotonic()
            late = now - next_t
            if late >= self.period:  # whole ticks missed: skip them, back on the grid
                skipped = int(late / self.period)
                self.overruns += skipped
                next_t += skipped * self.period
            if next_t > now:
                self._stop.wait(next_t - now)


class StepPhase:
    """Where the physics loop is in its period, so that other loops can start right after a step.

    A step is a few thousand small torch calls; each one gives up the interpreter lock and
    takes it back. Python work of another thread that overlaps the step (building messages,
    a render's set-up) makes the step wait for the lock at those points. Loops that call
    :meth:`after_step` before their work start it when a step has just ended, so that their
    interpreter-bound part falls in the idle part of the physics period.

    The physics loop calls :meth:`begin` and :meth:`end` around each step.
    """

    def __init__(self) -> None:
        self._cond = threading.Condition()
        self._running = False
        self._ended = 0

    def begin(self) -> None:
        with self._cond:
            self._running = True

    def end(self) -> None:
        with self._cond:
            self._running = False
            self._ended += 1
            self._cond.notify_all()

    @property
    def steps_ended(self) -> int:
        return self._ended

    def after_step(self, timeout: float) -> bool:
        """Block until the next step ends (True), or at most ``timeout`` seconds (False: no step
        ended, e.g. the physics loop is held by a reset)."""
        with self._cond:
            n = self._ended
            return self._cond.wait_for(lambda: self._ended != n, timeout)
