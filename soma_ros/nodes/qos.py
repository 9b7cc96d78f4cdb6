"""QoS profiles used by the soma_ros nodes."""

from rclpy.qos import (
    DurabilityPolicy,
    HistoryPolicy,
    QoSProfile,
    ReliabilityPolicy,
    qos_profile_sensor_data,
)

#: /joint_states input: best effort, keep last 10 -- matches sensor publishers and
#: also receives from reliable publishers (best-effort subscribers are compatible with both).
JOINT_STATES_QOS = qos_profile_sensor_data

#: Images and clouds out: reliable, keep last 1. A reliable writer matches both reliable
#: (RViz default) and best-effort (sensor QoS) readers; with KEEP_LAST 1 it overwrites
#: instead of blocking, so a slow subscriber never stalls the node.
SENSOR_OUT_QOS = QoSProfile(
    history=HistoryPolicy.KEEP_LAST, depth=1,
    reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.VOLATILE,
)

#: Latched-style topics (camera_info, the last splat cloud for late joiners): reliable, transient local.
LATCHED_QOS = QoSProfile(
    history=HistoryPolicy.KEEP_LAST, depth=1,
    reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL,
)

#: Status: reliable, keep last 10.
STATUS_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10, reliability=ReliabilityPolicy.RELIABLE)
