"""Write an episode as a rosbag2 directory, topic for topic like a real rig.

Topics (all messages of one frame share one header stamp, which is also the
bag timestamp):

===========================================  ===========================  ==========
topic                                        type                         encoding
===========================================  ===========================  ==========
/joint_states                                sensor_msgs/JointState       (effort: external torques)
/<cam>/color/image_raw                       sensor_msgs/Image            rgb8
/<cam>/color/camera_info                     sensor_msgs/CameraInfo       plumb_bob
/<cam>/aligned_depth_to_color/image_raw      sensor_msgs/Image            16UC1 (mm, 0 = no return)
/<cam>/aligned_depth_to_color/camera_info    sensor_msgs/CameraInfo       plumb_bob (the colour one's)
/<cam>/object_mask                           sensor_msgs/Image            mono8
/<cam>/robot_mask                            sensor_msgs/Image            mono8
/tf_static                                   tf2_msgs/TFMessage           (once, latched)
/tf                                          tf2_msgs/TFMessage           every URDF joint, each frame
/robot_description                           std_msgs/String              URDF (once, latched)
/world/object_points                         sensor_msgs/PointCloud2      x,y,z float32
===========================================  ===========================  ==========

``/tf`` carries the robot's links from the frame's joint state, as
robot_state_publisher computes them (:class:`~soma_ros.core.robot_frames.RobotFrames`);
its fixed joints are on ``/tf`` too, so ``/tf_static`` keeps only world -> robot base and
the cameras, and a camera's static chain ends at the link it is mounted on. The
depth is aligned to the colour image, so its camera_info is the colour one's
(what the RealSense driver publishes).

``/world/object_points`` carries the object's ground-truth vertices in
`world`. It is EVALUATION-ONLY: training code must never read it.
"""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np
from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

from .render import CameraFrame
from .scene import optical_frame_id
from .transforms import mat_to_quat

__all__ = ["BagRecorder", "STORAGES", "topics_for", "OBJECT_POINTS_TOPIC", "TYPESTORE"]

#: ``--storage`` choices.
STORAGES = {"sqlite3": StoragePlugin.SQLITE3, "mcap": StoragePlugin.MCAP}
#: Ground truth, evaluation only.
OBJECT_POINTS_TOPIC = "/world/object_points"
TYPESTORE = get_typestore(Stores.ROS2_JAZZY)
#: Topics recorded as a latched publisher offers them (written once).
LATCHED_TOPICS = ("/tf_static", "/robot_description")

_T = TYPESTORE.types
_Header = _T["std_msgs/msg/Header"]
_Time = _T["builtin_interfaces/msg/Time"]

_ZERO = QosTime(sec=0, nsec=0)
_INF = QosTime(sec=2147483647, nsec=4294967295)
#: What a latched tf_static publisher offers.
QOS_LATCHED = Qos(QosHistory.KEEP_LAST, 1, QosReliability.RELIABLE, QosDurability.TRANSIENT_LOCAL,
                  _INF, _INF, QosLiveliness.AUTOMATIC, _INF, False)
#: What the camera / joint state publishers offer.
QOS_SENSOR = Qos(QosHistory.KEEP_LAST, 10, QosReliability.RELIABLE, QosDurability.VOLATILE,
                 _INF, _INF, QosLiveliness.AUTOMATIC, _INF, False)


def topics_for(cameras: Sequence[str]) -> dict[str, str]:
    """{topic: message type} of a recorded episode."""
    t = {
        "/joint_states": "sensor_msgs/msg/JointState",
        "/tf_static": "tf2_msgs/msg/TFMessage",
        "/tf": "tf2_msgs/msg/TFMessage",
        "/robot_description": "std_msgs/msg/String",
        OBJECT_POINTS_TOPIC: "sensor_msgs/msg/PointCloud2",
    }
    for c in cameras:
        t[f"/{c}/color/image_raw"] = "sensor_msgs/msg/Image"
        t[f"/{c}/color/camera_info"] = "sensor_msgs/msg/CameraInfo"
        t[f"/{c}/aligned_depth_to_color/image_raw"] = "sensor_msgs/msg/Image"
        t[f"/{c}/aligned_depth_to_color/camera_info"] = "sensor_msgs/msg/CameraInfo"
        t[f"/{c}/object_mask"] = "sensor_msgs/msg/Image"
        t[f"/{c}/robot_mask"] = "sensor_msgs/msg/Image"
    return t


def _header(stamp_ns: int, frame_id: str):
    return _Header(stamp=_Time(sec=int(stamp_ns // 1_000_000_000), nanosec=int(stamp_ns % 1_000_000_000)), frame_id=frame_id)


def _image(stamp_ns: int, frame_id: str, arr: np.ndarray, encoding: str):
    arr = np.ascontiguousarray(arr)
    h, w = arr.shape[:2]
    data = arr.view(np.uint8).reshape(-1)
    return _T["sensor_msgs/msg/Image"](
        header=_header(stamp_ns, frame_id), height=h, width=w, encoding=encoding,
        is_bigendian=0, step=int(data.size // h), data=data,
    )


def _transform(stamp_ns: int, parent: str, child: str, T: np.ndarray):
    q = mat_to_quat(T[:3, :3])  # w, x, y, z
    tr = _T["geometry_msgs/msg/Transform"](
        translation=_T["geometry_msgs/msg/Vector3"](x=float(T[0, 3]), y=float(T[1, 3]), z=float(T[2, 3])),
        rotation=_T["geometry_msgs/msg/Quaternion"](x=float(q[1]), y=float(q[2]), z=float(q[3]), w=float(q[0])),
    )
    return _T["geometry_msgs/msg/TransformStamped"](header=_header(stamp_ns, parent), child_frame_id=child, transform=tr)


class BagRecorder:
    """Streams one episode into a new bag directory (must not exist). Use as a context manager."""

    def __init__(self, path: Path, cameras: Sequence[str], storage: str = "sqlite3") -> None:
        if storage not in STORAGES:
            raise ValueError(f"unknown storage '{storage}' (known: {', '.join(STORAGES)})")
        self.path = Path(path)
        if self.path.exists():
            raise FileExistsError(f"bag directory already exists: {self.path}")
        self.cameras = list(cameras)
        self._writer = Writer(self.path, version=9, storage_plugin=STORAGES[storage])
        self._conns: dict = {}
        self._pc_fields = [
            _T["sensor_msgs/msg/PointField"](name=n, offset=4 * i, datatype=7, count=1) for i, n in enumerate("xyz")
        ]

    def __enter__(self) -> "BagRecorder":
        self._writer.open()
        for topic, msgtype in topics_for(self.cameras).items():
            qos = QOS_LATCHED if topic in LATCHED_TOPICS else QOS_SENSOR
            self._conns[topic] = self._writer.add_connection(
                topic, msgtype, typestore=TYPESTORE, offered_qos_profiles=[qos]
            )
        return self

    def __exit__(self, *exc) -> None:
        self._writer.close()

    def _write(self, topic: str, stamp_ns: int, msg) -> None:
        conn = self._conns[topic]
        self._writer.write(conn, stamp_ns, TYPESTORE.serialize_cdr(msg, conn.msgtype))

    def write_tf_static(self, stamp_ns: int, transforms: list[tuple[str, str, np.ndarray]]) -> None:
        """One latched TFMessage of (parent, child, T [4, 4] parent <- child)."""
        msg = _T["tf2_msgs/msg/TFMessage"](transforms=[_transform(stamp_ns, p, c, T) for p, c, T in transforms])
        self._write("/tf_static", stamp_ns, msg)

    def write_robot_description(self, stamp_ns: int, urdf_text: str) -> None:
        """The latched /robot_description (the URDF's text)."""
        self._write("/robot_description", stamp_ns, _T["std_msgs/msg/String"](data=str(urdf_text)))

    def write_frame(
        self,
        stamp_ns: int,
        joint_names: list[str],
        position: np.ndarray,
        velocity: np.ndarray,
        effort: np.ndarray,
        frames: dict[str, CameraFrame],
        K: np.ndarray,
        object_points: np.ndarray,
        link_tf: Sequence[tuple[str, str, np.ndarray]] = (),
    ) -> None:
        """All messages of one frame, with one stamp. ``K`` [3, 3] is shared by the cameras;
        ``link_tf``: (parent, child, T [4, 4]) of the robot's joints, on /tf."""
        js = _T["sensor_msgs/msg/JointState"](
            header=_header(stamp_ns, ""),
            name=list(joint_names),
            position=np.asarray(position, np.float64),
            velocity=np.asarray(velocity, np.float64),
            effort=np.asarray(effort, np.float64),
        )
        self._write("/joint_states", stamp_ns, js)
        if link_tf:
            tf = _T["tf2_msgs/msg/TFMessage"](transforms=[_transform(stamp_ns, p, c, T) for p, c, T in link_tf])
            self._write("/tf", stamp_ns, tf)
        for cam in self.cameras:
            fr = frames[cam]
            fid = optical_frame_id(cam)
            h, w = fr.rgb.shape[:2]
            P = np.zeros((3, 4))
            P[:, :3] = K
            info = _T["sensor_msgs/msg/CameraInfo"](
                header=_header(stamp_ns, fid), height=h, width=w, distortion_model="plumb_bob",
                d=np.zeros(5), k=K.reshape(-1).astype(np.float64), r=np.eye(3).reshape(-1), p=P.reshape(-1),
                binning_x=0, binning_y=0,
                roi=_T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False),
            )
            self._write(f"/{cam}/color/image_raw", stamp_ns, _image(stamp_ns, fid, fr.rgb, "rgb8"))
            self._write(f"/{cam}/color/camera_info", stamp_ns, info)
            self._write(f"/{cam}/aligned_depth_to_color/camera_info", stamp_ns, info)
            self._write(
                f"/{cam}/aligned_depth_to_color/image_raw", stamp_ns,
                _image(stamp_ns, fid, fr.depth_mm.astype("<u2"), "16UC1"),
            )
            self._write(f"/{cam}/object_mask", stamp_ns, _image(stamp_ns, fid, fr.object_mask, "mono8"))
            self._write(f"/{cam}/robot_mask", stamp_ns, _image(stamp_ns, fid, fr.robot_mask, "mono8"))
        pts = np.ascontiguousarray(object_points, dtype="<f4")
        pc = _T["sensor_msgs/msg/PointCloud2"](
            header=_header(stamp_ns, "world"), height=1, width=int(len(pts)), fields=self._pc_fields,
            is_bigendian=False, point_step=12, row_step=12 * int(len(pts)), data=pts.view(np.uint8).reshape(-1),
            is_dense=True,
        )
        self._write(OBJECT_POINTS_TOPIC, stamp_ns, pc)
