"""soma_bag_player: drive the live simulator from a rosbag2, as a robot would.

Publishes a bag's ``/joint_states`` (and optionally its camera topics and
``/tf_static``) into the ROS graph with the bag's original timing: the gaps
between the recorded receive timestamps, divided by ``--rate``. Scheduling is
absolute (message k is due at start + (t_k - t_0) / rate), so a late message
never delays the ones after it and the total duration does not drift.

Usage::

    soma_bag_player BAG [--rate 2.0] [--loop] [--start-offset S]
                        [--topics /joint_states /camera/color/image_raw ...]
                        [--cameras] [--tf-static]
                        [--wait-for-subscribers N] [--wait-timeout S]
                        [--restamp | --no-restamp] [--ros-args ...]

- Header stamps are rewritten by default (``--restamp``): a live node compares
  stamps with its own clock. The new stamp is the publish time plus the
  message's latency in the recording (original stamp - original receive
  time) when that latency is plausible (|latency| < 5 s), else the publish
  time. ``--no-restamp`` keeps the recorded stamps.
- ``/tf_static``, and any topic the recording publisher offered as transient
  local, is published latched (reliable, transient local, the topic's whole
  history). Latched messages recorded before ``--start-offset`` are published
  at the start.
- ``/world/object_points`` (the reference world's ground truth) is never read.
- ``/joint_states`` goes out reliable with keep-last 100: sensor-data (best
  effort) and reliable subscribers both match.
"""

from __future__ import annotations

import argparse
import signal
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterator, Optional, Sequence
from ..core.errors import NodeError
from .arguments import non_negative_float, non_negative_int, positive_float

PROG = "soma_bag_player"
JOINT_STATES = "/joint_states"
#: Topics the player refuses to read: the reference world's ground truth.
GROUND_TRUTH_TOPICS = ("/world/object_points",)
#: Always published latched.
LATCHED_TOPICS = ("/tf_static",)
CAMERA_TYPES = ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage", "sensor_msgs/msg/CameraInfo")
#: A recorded (stamp - receive time) within this bound is kept as latency by --restamp.
MAX_RESTAMP_LATENCY_NS = 5_000_000_000
JOINT_STATES_DEPTH = 100
SUBSCRIBER_SETTLE_S = 0.3  # readiness must hold this long before playing (see wait_for_subscribers)
OTHER_DEPTH = 10
BEHIND_WARN_S = 0.05


class PlayerError(NodeError):
    """A problem with the bag or the arguments; its message is one line for the user."""


class StopFlag:
    """A stop request set from SIGINT/SIGTERM handlers.

    A plain flag, not a threading.Event: a Python signal handler runs in the
    main thread between bytecodes, and Event.set() would deadlock if the main
    thread was inside Event.wait() holding the event's lock at that moment.
    Waits poll it every POLL_S seconds.
    """

    POLL_S = 0.05

    def __init__(self) -> None:
        self._set = False
        self._previous: dict = {}

    def set(self, *_: Any) -> None:
        self._set = True

    def is_set(self) -> bool:
        return self._set

    def wait(self, timeout: float) -> bool:
        """Sleep up to `timeout` seconds (less if stop is requested); True if stop was requested."""
        end = time.monotonic() + timeout
        while not self._set:
            left = end - time.monotonic()
            if left <= 0:
                break
            time.sleep(min(left, self.POLL_S))
        return self._set

    def install(self) -> "StopFlag":
        """Route SIGINT and SIGTERM here (also when the parent shell started us with SIGINT ignored)."""
        for sig in (signal.SIGINT, signal.SIGTERM):
            self._previous[sig] = signal.signal(sig, self.set)
        return self

    def restore(self) -> None:
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)
        self._previous.clear()


def run_with_stop(body: Callable[[Optional[list[str]], "StopFlag"], int], argv: Optional[list[str]]) -> int:
    """Run a command's ``body(argv, stop)`` with SIGINT/SIGTERM routed to a StopFlag, installed
    first: a signal during the (slow) imports inside ``body`` must not be lost."""
    stop = StopFlag().install()
    try:
        return body(argv, stop)
    finally:
        stop.restore()


# ----------------------------------------------------------------- arguments
def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog=PROG, description="Publish a rosbag2's /joint_states (and cameras, /tf_static) with its original timing.")
    p.add_argument("bag", help="rosbag2 directory (holding metadata.yaml)")
    p.add_argument("--topics", nargs="+", metavar="TOPIC",
                   help=f"topics to play (default: {JOINT_STATES})")
    p.add_argument("--cameras", action="store_true",
                   help="also play every Image / CompressedImage / CameraInfo topic of the bag")
    p.add_argument("--tf-static", action="store_true", help="also play /tf_static (latched)")
    p.add_argument("--rate", type=positive_float, default=1.0, help="playback speed factor (2.0: twice as fast)")
    p.add_argument("--loop", action="store_true", help="play again from the start offset until interrupted")
    p.add_argument("--start-offset", type=non_negative_float, default=0.0, metavar="S",
                   help="skip the first S seconds of the bag")
    p.add_argument("--wait-for-subscribers", type=non_negative_int, default=0, metavar="N",
                   help=f"before playing, wait until N subscribers matched on {JOINT_STATES} "
                        "(and every QoS-compatible subscriber already in the graph on each played topic, for 0.3 s)")
    p.add_argument("--wait-timeout", type=positive_float, default=30.0, metavar="S",
                   help="give up waiting for subscribers after S seconds (exit 1)")
    stamp = p.add_mutually_exclusive_group()
    stamp.add_argument("--restamp", dest="restamp", action="store_true", default=True,
                       help="rewrite header stamps to the publish time plus the recorded latency (default)")
    stamp.add_argument("--no-restamp", dest="restamp", action="store_false", help="keep the recorded header stamps")
    return p


# ----------------------------------------------------------------------- bag
@dataclass
class PlayedTopic:
    topic: str
    msgtype: str
    connections: list = field(default_factory=list)
    latched: bool = False
    count: int = 0  # messages in the bag


def _recorded_transient_local(connections: Sequence[Any]) -> bool:
    from rosbags.interfaces import QosDurability

    profiles = [q for c in connections for q in (getattr(c.ext, "offered_qos_profiles", None) or [])]
    return bool(profiles) and all(q.durability == QosDurability.TRANSIENT_LOCAL for q in profiles)


def select_topics(reader: Any, args: argparse.Namespace) -> list[PlayedTopic]:
    """The bag topics to play (PlayerError names a missing or forbidden topic)."""
    by_topic: dict[str, list] = {}
    for c in reader.connections:
        by_topic.setdefault(c.topic, []).append(c)
    available = ", ".join(sorted(by_topic)) or "none"

    wanted: list[str] = list(args.topics) if args.topics else [JOINT_STATES]
    if args.cameras:
        cams = sorted(t for t, cs in by_topic.items()
                      if cs[0].msgtype in CAMERA_TYPES and t not in GROUND_TRUTH_TOPICS)
        if not cams:
            raise PlayerError(f"--cameras: no Image/CompressedImage/CameraInfo topic in the bag (it has: {available})")
        wanted += cams
    if args.tf_static:
        wanted.append("/tf_static")

    out: list[PlayedTopic] = []
    seen: set[str] = set()
    for topic in wanted:
        if topic in seen:
            continue
        seen.add(topic)
        if topic in GROUND_TRUTH_TOPICS:
            raise PlayerError(f"{topic} is the reference world's ground truth and is never played")
        conns = by_topic.get(topic)
        if not conns:
            raise PlayerError(f"topic {topic} not in the bag (it has: {available})")
        types = {c.msgtype for c in conns}
        if len(types) != 1:
            raise PlayerError(f"topic {topic} has several types in the bag: {', '.join(sorted(types))}")
        out.append(PlayedTopic(
            topic=topic, msgtype=conns[0].msgtype, connections=conns,
            latched=topic in LATCHED_TOPICS or _recorded_transient_local(conns),
            count=sum(c.msgcount for c in conns),
        ))
    return out


def open_bag(path: str) -> Any:
    """An open rosbags AnyReader (PlayerError on a missing or unreadable bag)."""
    from rosbags.highlevel import AnyReader

    from ..bagtypes import typestore

    p = Path(path)
    if not p.exists():
        raise PlayerError(f"bag not found: {p}")
    if p.is_file() and p.suffix in (".db3", ".mcap", ".yaml"):
        p = p.parent
    try:
        reader = AnyReader([p], default_typestore=typestore())
        reader.open()
    except Exception as exc:  # rosbags raises several unrelated types for bad bags
        detail = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise PlayerError(f"cannot open bag {p}: {detail}") from None
    return reader


# ------------------------------------------------------------------- restamp
def _header_walker(cls: type, cache: dict) -> Optional[Callable[[Any, Callable[[Any], None]], None]]:
    """A function calling fn(header) for every std_msgs/Header inside a message of `cls` (None: has none)."""
    if cls in cache:
        return cache[cls]
    from rosidl_parser import definition as idl

    from .rosbags_bridge import rclpy_class

    cache[cls] = None  # recursion guard
    steps: list[Callable[[Any, Callable[[Any], None]], None]] = []
    for name, slot in zip(cls.get_fields_and_field_types().keys(), cls.SLOT_TYPES):
        target = slot.value_type if isinstance(slot, idl.AbstractNestedType) else slot
        if not isinstance(target, idl.NamespacedType):
            continue
        sub_name = "/".join([*target.namespaces, target.name])
        many = isinstance(slot, idl.AbstractNestedType)
        if sub_name == "std_msgs/msg/Header":
            if many:
                steps.append(lambda m, fn, n=name: [fn(h) for h in getattr(m, n)])
            else:
                steps.append(lambda m, fn, n=name: fn(getattr(m, n)))
            continue
        inner = _header_walker(rclpy_class(sub_name), cache)
        if inner is None:
            continue
        if many:
            steps.append(lambda m, fn, n=name, w=inner: [w(x, fn) for x in getattr(m, n)])
        else:
            steps.append(lambda m, fn, n=name, w=inner: w(getattr(m, n), fn))
    if not steps:
        return None  # cache[cls] stays None

    def walker(m: Any, fn: Callable[[Any], None], _steps=tuple(steps)) -> None:
        for step in _steps:
            step(m, fn)

    cache[cls] = walker
    return walker


# -------------------------------------------------------------------- player
@dataclass
class PlayStats:
    counts: dict = field(default_factory=dict)
    wall_s: float = 0.0
    bag_s: float = 0.0
    loops: int = 0
    skipped: int = 0
    max_late_s: float = 0.0

    @property
    def total(self) -> int:
        return sum(self.counts.values())

    def summary(self, rate: float) -> str:
        per_topic = ", ".join(f"{t} {n}" for t, n in self.counts.items())
        achieved = f"{self.bag_s / self.wall_s:.2f}x" if self.wall_s > 0 else "n/a"
        extra = f", {self.loops} loops" if self.loops > 1 else ""
        extra += f", {self.skipped} undecodable skipped" if self.skipped else ""
        return (f"{PROG}: published {self.total} messages ({per_topic}) in {self.wall_s:.3f} s wall "
                f"for {self.bag_s:.3f} s of bag: achieved rate {achieved} (requested {rate:.2f}x), "
                f"max lateness {self.max_late_s * 1e3:.1f} ms{extra}")


class BagPlayer:
    """Owns the rclpy node, its publishers and the playback loop."""

    def __init__(self, reader: Any, topics: list[PlayedTopic], args: argparse.Namespace, context: Any,
                 stop: Optional[StopFlag] = None) -> None:
        from rclpy.node import Node
        from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

        from .rosbags_bridge import rclpy_class

        self.reader = reader
        self.topics = topics
        self.args = args
        self.stop = stop if stop is not None else StopFlag()
        self.node = Node(PROG, context=context)
        self.log = self.node.get_logger()
        self.classes: dict[str, type] = {}
        self.publishers: dict[str, Any] = {}
        self._walkers: dict = {}
        for t in topics:
            cls = rclpy_class(t.msgtype)
            self.classes[t.topic] = cls
            if t.latched:
                qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=max(1, min(t.count, 1000)),
                                 reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
            else:
                qos = QoSProfile(history=HistoryPolicy.KEEP_LAST,
                                 depth=JOINT_STATES_DEPTH if t.topic == JOINT_STATES else OTHER_DEPTH,
                                 reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.VOLATILE)
            self.publishers[t.topic] = self.node.create_publisher(cls, t.topic, qos)
        self.stats = PlayStats(counts={t.topic: 0 for t in topics})

    # ------------------------------------------------------------ waiting
    def wait_for_subscribers(self, n: int, timeout: float) -> None:
        """Block until `n` subscribers matched on the main topic and every known subscriber on the others."""
        main = JOINT_STATES if JOINT_STATES in self.publishers else self.topics[0].topic
        deadline = time.monotonic() + timeout

        def ready() -> bool:
            if self.publishers[main].get_subscription_count() < n:
                return False
            return self._all_matched()

        # A node's subscriptions reach the graph one by one: the main topic can match before the
        # same node's other subscriptions are known, so readiness must hold for a settle period.
        ready_since: Optional[float] = None
        while True:
            now = time.monotonic()
            if ready():
                ready_since = now if ready_since is None else ready_since
                if now - ready_since >= SUBSCRIBER_SETTLE_S:
                    return
            else:
                ready_since = None
            if self.stop.is_set():
                return
            if time.monotonic() >= deadline:
                have = self.publishers[main].get_subscription_count()
                raise PlayerError(f"timed out after {timeout:g} s waiting for {n} subscriber(s) on {main} "
                                  f"({have} matched)")
            self.stop.wait(0.02)

    # -------------------------------------------------------------- stamps
    def _restamp(self, msg: Any, log_ns: int) -> None:
        walker = _header_walker(type(msg), self._walkers)
        if walker is None:
            return
        now_ns = self.node.get_clock().now().nanoseconds

        def fix(header: Any) -> None:
            orig = int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)
            latency = orig - log_ns
            ns = now_ns + latency if abs(latency) < MAX_RESTAMP_LATENCY_NS else now_ns
            header.stamp.sec, header.stamp.nanosec = divmod(max(ns, 0), 1_000_000_000)

        walker(msg, fix)

    # ------------------------------------------------------------ playback
    def _messages(self, start_ns: int, first_pass: bool) -> Iterator[tuple[str, int, Any, bool]]:
        """(topic, log time, rclpy message, due now) in log-time order; latched messages before start first."""
        from .rosbags_bridge import to_rclpy

        topic_of = {c.id: t.topic for t in self.topics for c in t.connections}

        def convert(conn: Any, raw: bytes) -> Any:
            try:
                return to_rclpy(self.reader.deserialize(raw, conn.msgtype), self.classes[conn.topic])
            except Exception as exc:
                self.stats.skipped += 1
                self.log.warning(f"skipped an undecodable {conn.topic} message: {exc}", throttle_duration_sec=2.0)
                return None

        if first_pass and start_ns > self.reader.start_time:
            latched = [c for t in self.topics if t.latched for c in t.connections]
            if latched:
                for conn, t, raw in self.reader.messages(connections=latched, stop=start_ns):
                    msg = convert(conn, raw)
                    if msg is not None:
                        yield topic_of[conn.id], t, msg, True
        conns = [c for t in self.topics for c in t.connections]
        for conn, t, raw in self.reader.messages(connections=conns, start=start_ns):
            msg = convert(conn, raw)
            if msg is not None:
                yield topic_of[conn.id], t, msg, False

    def play_once(self, first_pass: bool) -> tuple[int, float]:
        """One pass over the bag: (messages published, mean scheduled gap in wall seconds)."""
        rate = self.args.rate
        start_ns = self.reader.start_time + int(round(self.args.start_offset * 1e9))
        origin_ns: Optional[int] = None
        wall0 = first_wall = last_wall = 0.0
        first_t: Optional[int] = None
        last_t = 0
        published = scheduled = 0
        for topic, t, msg, now_due in self._messages(start_ns, first_pass):
            if not now_due:
                if origin_ns is None:
                    origin_ns, wall0 = t, time.monotonic()
                due = wall0 + (t - origin_ns) / 1e9 / rate
                delay = due - time.monotonic()
                if delay > 0 and self.stop.wait(delay):
                    break
                late = time.monotonic() - due
                if late > self.stats.max_late_s:
                    self.stats.max_late_s = late
                if late > BEHIND_WARN_S:
                    self.log.warning(f"playback behind schedule by {late * 1e3:.0f} ms on {topic}",
                                     throttle_duration_sec=2.0)
            if self.stop.is_set():
                break
            if self.args.restamp:
                self._restamp(msg, t)
            self.publishers[topic].publish(msg)
            published += 1
            self.stats.counts[topic] += 1
            if not now_due:
                last_wall = time.monotonic()
                if first_t is None:
                    first_t, first_wall = t, last_wall
                last_t = t
                scheduled += 1
        if published:
            self.stats.loops += 1
        if first_t is None:
            return published, 0.0
        self.stats.wall_s += last_wall - first_wall
        self.stats.bag_s += (last_t - first_t) / 1e9
        mean_gap = (last_t - first_t) / 1e9 / rate / (scheduled - 1) if scheduled > 1 else 0.0
        return published, mean_gap

    def play(self) -> PlayStats:
        if self.args.wait_for_subscribers > 0:
            self.wait_for_subscribers(self.args.wait_for_subscribers, self.args.wait_timeout)
        first = True
        while not self.stop.is_set():
            published, mean_gap = self.play_once(first)
            if published == 0 and first and not self.stop.is_set():
                raise PlayerError(f"nothing to play after --start-offset {self.args.start_offset:g} s")
            first = False
            if not self.args.loop:
                break
            # The loop seam keeps the stream's rhythm: one mean gap (1 s / rate for a lone message).
            self.stop.wait(mean_gap if mean_gap > 0 else 1.0 / self.args.rate)
        self.flush()
        return self.stats

    def _all_matched(self) -> bool:
        """Every played topic's publisher matched all QoS-compatible subscriptions in the graph."""
        from rclpy.qos import QoSCompatibility, qos_check_compatible

        for topic, pub in self.publishers.items():
            offered = pub.qos_profile
            known = sum(1 for info in self.node.get_subscriptions_info_by_topic(topic)
                        if qos_check_compatible(offered, info.qos_profile)[0] != QoSCompatibility.ERROR)
            if pub.get_subscription_count() < known:
                return False
        return True

    def flush(self, timeout_s: float = 2.0) -> None:
        """Before the node goes away: let subscriptions that joined the graph during playback match (a
        latched message still reaches them) and reliable subscribers acknowledge the last messages."""
        from rclpy.duration import Duration

        deadline = time.monotonic() + timeout_s
        while not self._all_matched() and time.monotonic() < deadline:
            time.sleep(0.02)
        for pub in self.publishers.values():
            left = deadline - time.monotonic()
            if left <= 0:
                break
            pub.wait_for_all_acked(Duration(nanoseconds=int(left * 1e9)))

    def destroy(self) -> None:
        self.node.destroy_node()


# ---------------------------------------------------------------------- main
def main(argv: Optional[list[str]] = None) -> int:
    """Entry point; `argv` excludes the program name (default: sys.argv[1:])."""
    return run_with_stop(_main, argv)


def _main(argv: Optional[list[str]], stop: StopFlag) -> int:
    from rclpy.utilities import remove_ros_args

    full = [PROG, *(sys.argv[1:] if argv is None else argv)]
    args = build_parser().parse_args(remove_ros_args(full)[1:])

    reader = None
    try:
        reader = open_bag(args.bag)
        topics = select_topics(reader, args)
        from .rosbags_bridge import MessageTypeError, rclpy_class

        for t in topics:
            try:
                rclpy_class(t.msgtype)
            except MessageTypeError as exc:
                raise PlayerError(f"topic {t.topic}: {exc}") from None
    except PlayerError as exc:
        print(f"{PROG}: error: {exc}", file=sys.stderr)
        if reader is not None:
            reader.close()
        return 1

    import rclpy
    from rclpy.context import Context
    from rclpy.signals import SignalHandlerOptions

    context = Context()
    rclpy.init(args=full, context=context, signal_handler_options=SignalHandlerOptions.NO)
    player: Optional[BagPlayer] = None
    rc = 0
    try:
        player = BagPlayer(reader, topics, args, context, stop)
        stats = player.play()
        print(stats.summary(args.rate), flush=True)
    except PlayerError as exc:
        print(f"{PROG}: error: {exc}", file=sys.stderr)
        rc = 1
    finally:
        if player is not None:
            player.destroy()
        reader.close()
        if context.ok():
            rclpy.shutdown(context=context)
    return rc


if __name__ == "__main__":
    sys.exit(main())
