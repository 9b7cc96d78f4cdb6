"""soma_recorder: record what the simulator publishes into a rosbag2.

Usage::

    python -m soma_ros.nodes.recorder --out BAG --topics /soma/splats /soma/status[:soma_msgs/msg/SimStatus] ...
                                      [--duration S] [--max-messages N] [--storage sqlite3|mcap]
                                      [--discovery-timeout S] [--queue N] [--ros-args ...]

- A topic's type is discovered from the graph (waiting up to
  ``--discovery-timeout``) or given as ``/topic:pkg/msg/Type``. A typed topic
  still without a publisher when the timeout ends is subscribed best effort /
  volatile, which matches any publisher that appears later; an untyped one is
  an error.
- The subscriber QoS follows the publishers found: reliable if all of them are
  reliable (else best effort), transient local if all of them are (so latched
  messages are recorded too). The publishers' offered QoS goes into the bag's
  metadata, as rosbag2 does.
- Messages are taken serialised (no deserialisation) and written as they
  arrive, stamped with the node clock at reception: memory stays bounded by
  the DDS queue (``--queue``) and the storage's write buffer.
- SIGINT / SIGTERM, ``--duration`` or ``--max-messages`` stop it: messages
  already received are drained, the bag is closed (metadata.yaml written) and
  a one-line summary printed.
- Message definitions come from the rosbags typestore with soma_msgs
  registered (:func:`soma_ros.bagtypes.typestore`), so the bag is
  self-describing for rosbags, Foxglove and ``ros2 bag``.
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Optional

from .arguments import positive_float, positive_int
from .bag_player import StopFlag, run_with_stop
from ..core.errors import NodeError

PROG = "soma_recorder"
DRAIN_S = 2.0


class RecorderError(NodeError):
    """A problem the user must fix; its message is one line."""


# ----------------------------------------------------------------- arguments
def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog=PROG, description="Record ROS 2 topics into a rosbag2 (rosbags writer, format 9).")
    p.add_argument("--out", required=True, help="output bag directory (must not exist)")
    p.add_argument("--topics", required=True, nargs="+", metavar="TOPIC[:TYPE]",
                   help="topics to record; with TYPE (pkg/msg/Name) a topic without publishers yet is recorded too")
    p.add_argument("--duration", type=positive_float, metavar="S", help="stop after S seconds of recording")
    p.add_argument("--max-messages", type=positive_int, metavar="N", help="stop after N messages in total")
    p.add_argument("--storage", choices=("sqlite3", "mcap"), default="sqlite3", help="rosbag2 storage plugin")
    p.add_argument("--discovery-timeout", type=positive_float, default=10.0, metavar="S",
                   help="wait at most S seconds for the topics' publishers to appear in the graph")
    p.add_argument("--queue", type=positive_int, default=100, metavar="N", help="subscription history depth")
    return p


@dataclass
class TopicSpec:
    topic: str
    msgtype: Optional[str] = None


def parse_topic_specs(items: list[str]) -> list[TopicSpec]:
    specs: list[TopicSpec] = []
    seen: set[str] = set()
    for item in items:
        topic, _, msgtype = item.partition(":")
        if not topic.startswith("/") or len(topic) < 2:
            raise RecorderError(f"not an absolute topic name: {item!r}")
        if topic in seen:
            continue
        seen.add(topic)
        specs.append(TopicSpec(topic, msgtype or None))
    return specs


def check_type(msgtype: str, store: Any) -> None:
    """RecorderError unless both rclpy and the typestore know `msgtype`."""
    from .rosbags_bridge import MessageTypeError, rclpy_class

    try:
        rclpy_class(msgtype)
    except MessageTypeError as exc:
        raise RecorderError(str(exc)) from None
    if msgtype not in store.fielddefs:
        raise RecorderError(f"message type {msgtype} is not in the rosbags typestore (no definition to embed)")


# ----------------------------------------------------------------------- qos
def to_rosbags_qos(q: Any) -> Any:
    """An rclpy QoSProfile as rosbags' Qos (for the bag's offered_qos_profiles)."""
    from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime

    def t(d: Any) -> QosTime:
        sec, nsec = divmod(int(d.nanoseconds), 1_000_000_000)
        return QosTime(sec=sec, nsec=nsec)

    def enum(cls: Any, value: Any) -> Any:
        try:
            return cls(int(value))
        except ValueError:
            return cls.UNKNOWN

    return Qos(
        history=enum(QosHistory, q.history), depth=int(q.depth),
        reliability=enum(QosReliability, q.reliability), durability=enum(QosDurability, q.durability),
        deadline=t(q.deadline), lifespan=t(q.lifespan), liveliness=enum(QosLiveliness, q.liveliness),
        liveliness_lease_duration=t(q.liveliness_lease_duration),
        avoid_ros_namespace_conventions=bool(q.avoid_ros_namespace_conventions),
    )


def subscriber_qos(publisher_qos: list, depth: int) -> Any:
    """Reliable / transient local only when every publisher offers it; best effort / volatile match anyone."""
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

    reliable = bool(publisher_qos) and all(q.reliability == ReliabilityPolicy.RELIABLE for q in publisher_qos)
    latched = bool(publisher_qos) and all(q.durability == DurabilityPolicy.TRANSIENT_LOCAL for q in publisher_qos)
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST, depth=depth,
        reliability=ReliabilityPolicy.RELIABLE if reliable else ReliabilityPolicy.BEST_EFFORT,
        durability=DurabilityPolicy.TRANSIENT_LOCAL if latched else DurabilityPolicy.VOLATILE,
    )


def _qos_words(q: Any) -> str:
    from rclpy.qos import DurabilityPolicy, ReliabilityPolicy

    rel = "reliable" if q.reliability == ReliabilityPolicy.RELIABLE else "best effort"
    dur = "transient local" if q.durability == DurabilityPolicy.TRANSIENT_LOCAL else "volatile"
    return f"{rel}, {dur}"


# ------------------------------------------------------------------ recorder
@dataclass
class Recorded:
    topic: str
    msgtype: str
    qos: Any
    offered: list = field(default_factory=list)
    connection: Any = None
    count: int = 0


class Recorder:
    """Discovers the topics, owns the bag writer and the raw subscriptions."""

    def __init__(self, node: Any, args: argparse.Namespace, specs: list[TopicSpec], store: Any,
                 stop: Optional[StopFlag] = None) -> None:
        self.node = node
        self.args = args
        self.specs = specs
        self.store = store
        self.log = node.get_logger()
        self.stop = stop if stop is not None else StopFlag()
        self.writer: Any = None
        self.topics: list[Recorded] = []
        self.taken = 0  # callbacks run, written or not
        self.written = 0
        self.bytes = 0
        self.error: Optional[str] = None
        self.t_start = 0.0
        self.t_stop = 0.0

    # ----------------------------------------------------------- discovery
    def discover(self) -> None:
        """Types and publisher QoS of every topic (RecorderError names a topic that never showed up)."""
        deadline = time.monotonic() + self.args.discovery_timeout
        pending = {s.topic: s for s in self.specs}
        found: dict[str, Recorded] = {}
        while pending:
            graph = dict(self.node.get_topic_names_and_types())
            for topic in list(pending):
                spec = pending[topic]
                infos = self.node.get_publishers_info_by_topic(topic)
                if not infos:
                    continue
                types = sorted(set(graph.get(topic, [])) | {i.topic_type for i in infos})
                msgtype = spec.msgtype
                if msgtype is None:
                    if len(types) != 1:
                        raise RecorderError(f"topic {topic} is published with several types: {', '.join(types)}")
                    msgtype = types[0]
                elif msgtype not in types:
                    raise RecorderError(f"topic {topic} is published as {', '.join(types)}, not {msgtype}")
                offered = [i.qos_profile for i in infos]
                found[topic] = Recorded(topic, msgtype, subscriber_qos(offered, self.args.queue), offered)
                del pending[topic]
            if not pending or self.stop.is_set():
                break
            if time.monotonic() >= deadline:
                untyped = [t for t, s in pending.items() if s.msgtype is None]
                if untyped:
                    raise RecorderError(
                        f"topic {', '.join(untyped)} not found in the ROS graph within "
                        f"{self.args.discovery_timeout:g} s (give /topic:pkg/msg/Type to record it anyway)")
                for topic, spec in pending.items():
                    self.log.warning(f"{topic}: no publisher yet; subscribing best effort as {spec.msgtype}")
                    found[topic] = Recorded(topic, spec.msgtype, subscriber_qos([], self.args.queue))
                pending.clear()
                break
            self.stop.wait(0.05)
        if self.stop.is_set():
            raise RecorderError("interrupted while waiting for the topics to appear")
        for spec in self.specs:
            check_type(found[spec.topic].msgtype, self.store)
        self.topics = [found[s.topic] for s in self.specs]

    # ------------------------------------------------------------- writing
    def open(self, out: Path) -> None:
        from rosbags.rosbag2 import StoragePlugin, Writer, WriterError

        plugin = StoragePlugin.MCAP if self.args.storage == "mcap" else StoragePlugin.SQLITE3
        try:
            writer = Writer(out, version=9, storage_plugin=plugin)
            writer.open()
        except (WriterError, OSError) as exc:
            raise RecorderError(f"cannot create bag {out}: {exc}") from None
        self.writer = writer
        for rec in self.topics:
            rec.connection = self.writer.add_connection(
                rec.topic, rec.msgtype, typestore=self.store,
                offered_qos_profiles=[to_rosbags_qos(q) for q in rec.offered])

    def subscribe(self) -> None:
        from .rosbags_bridge import rclpy_class

        for rec in self.topics:
            self.node.create_subscription(
                rclpy_class(rec.msgtype), rec.topic, lambda raw, r=rec: self._on_message(r, raw), rec.qos, raw=True)
            self.log.info(f"recording {rec.topic} [{rec.msgtype}] ({_qos_words(rec.qos)})")
        self.t_start = time.monotonic()

    def _on_message(self, rec: Recorded, raw: bytes) -> None:
        self.taken += 1
        if self.error is not None:
            return
        limit = self.args.max_messages
        if limit is not None and self.written >= limit:
            return
        stamp = self.node.get_clock().now().nanoseconds
        try:
            self.writer.write(rec.connection, stamp, raw)
        except Exception as exc:  # disk full, closed storage, ...
            self.error = f"writing {rec.topic} failed: {exc}"
            self.stop.set()
            return
        rec.count += 1
        self.written += 1
        self.bytes += len(raw)
        if limit is not None and self.written >= limit:
            self.stop.set()

    def run(self, executor: Any) -> None:
        duration = self.args.duration
        while not self.stop.is_set():
            executor.spin_once(timeout_sec=0.1)
            if duration is not None and time.monotonic() - self.t_start >= duration:
                self.stop.set()
        self.t_stop = time.monotonic()
        limit = self.args.max_messages
        if limit is None or self.written < limit:
            self.drain(executor)

    def drain(self, executor: Any) -> None:
        """Write what DDS has already delivered to the subscriptions (bounded in time)."""
        deadline = time.monotonic() + DRAIN_S
        idle = 0
        while idle < 2 and time.monotonic() < deadline and self.error is None:
            before = self.taken
            executor.spin_once(timeout_sec=0.02)
            idle = idle + 1 if self.taken == before else 0

    def close(self) -> None:
        if self.writer is not None:
            self.writer.close()
            self.writer = None

    def summary(self, out: Path) -> str:
        wall = max(self.t_stop - self.t_start, 1e-9)
        per_topic = ", ".join(f"{r.topic} {r.count}" for r in self.topics)
        mb = self.bytes / 1e6
        return (f"{PROG}: wrote {self.written} messages ({per_topic}), {mb:.2f} MB in {wall:.2f} s "
                f"({self.written / wall:.1f} msg/s, {mb / wall:.2f} MB/s) to {out} [{self.args.storage}]")


# ---------------------------------------------------------------------- main
def main(argv: Optional[list[str]] = None) -> int:
    """Entry point; `argv` excludes the program name (default: sys.argv[1:])."""
    return run_with_stop(_main, argv)


def _main(argv: Optional[list[str]], stop: StopFlag) -> int:
    from rclpy.utilities import remove_ros_args

    full = [PROG, *(sys.argv[1:] if argv is None else argv)]
    args = build_parser().parse_args(remove_ros_args(full)[1:])
    out = Path(args.out)
    try:
        if out.exists():
            raise RecorderError(f"output bag already exists: {out}")
        if not out.parent.is_dir():
            raise RecorderError(f"output folder does not exist: {out.parent}")
        specs = parse_topic_specs(args.topics)
        from ..bagtypes import typestore

        store = typestore()
        for s in specs:
            if s.msgtype:
                check_type(s.msgtype, store)
    except RecorderError as exc:
        print(f"{PROG}: error: {exc}", file=sys.stderr)
        return 1

    import rclpy
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node
    from rclpy.signals import SignalHandlerOptions

    context = Context()
    rclpy.init(args=full, context=context, signal_handler_options=SignalHandlerOptions.NO)
    node = Node(PROG, context=context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    recorder = Recorder(node, args, specs, store, stop)
    rc = 0
    try:
        recorder.discover()
        recorder.open(out)
        recorder.subscribe()
        recorder.run(executor)
        if recorder.error is not None:
            raise RecorderError(recorder.error)
    except RecorderError as exc:
        print(f"{PROG}: error: {exc}", file=sys.stderr)
        rc = 1
    finally:
        try:
            recorder.close()
        finally:
            executor.shutdown()
            node.destroy_node()
            if context.ok():
                rclpy.shutdown(context=context)
    if recorder.t_start:
        print(recorder.summary(out), flush=True)
    return rc


if __name__ == "__main__":
    sys.exit(main())
