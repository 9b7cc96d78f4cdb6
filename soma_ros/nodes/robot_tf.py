"""The live node's TF tree and /robot_description, as robot_state_publisher would publish them.

One tree, rooted at the world frame::

    world ─┬─ soma_sim                          (identity: the simulation frame)
           ├─ <sim>/<cam>_optical               fixed cameras of the scene bundle
           └─ <base_link> ─ ... URDF links ...  robot_state_publisher's transforms
                  └─ <mount link> ─ <sim>/<cam>_optical   cameras mounted on a link

``/tf_static`` (latched, one message): world -> sim frame, world -> robot base
(the scene's robot -> simulation transform), every fixed URDF joint, every
camera. ``/tf``: every movable URDF joint from the joint state a step used,
stamped with that step's stamp (:meth:`RobotTf.publish`), so a rendered image
and the robot links it shows share one stamp. ``/robot_description``
(std_msgs/String, transient local): the URDF, mesh references made absolute.

With ``publish_robot=False`` (a real robot's robot_state_publisher already
publishes the links) only the world -> sim and the camera transforms are
published: the mounted cameras then hang off the real robot's links.

TF carries no scale: a scene whose robot -> simulation transform is a
similarity with scale s != 1 gets its rotation and translation only, and the
node logs that the robot's frames are off by that scale.
"""

from __future__ import annotations

from typing import Optional

import numpy as np
from std_msgs.msg import String
from tf2_msgs.msg import TFMessage

from ..core.robot_frames import RobotFrames, robot_description
from .conversions import matrix_to_tf, stamp_from_ns
from .qos import LATCHED_QOS

__all__ = ["RobotTf", "camera_frame_id"]


def camera_frame_id(sim_frame: str, cam: str) -> str:
    """The optical frame of a simulated camera (images, depth, camera_info)."""
    return f"{sim_frame}/{cam}_optical"


def _transforms(edges, stamp) -> list:
    """[(parent, child, T [1, 4, 4])] -> TransformStamped list, the quaternions in one batched call."""
    import torch
    from geometry_msgs.msg import TransformStamped

    from ..core.geometry import rotmat_to_quat

    if not edges:
        return []
    T = np.stack([t[0] for _, _, t in edges])  # [J, 4, 4]
    q = rotmat_to_quat(torch.from_numpy(T[:, :3, :3])).numpy()  # [J, 4] w, x, y, z
    out = []
    for (parent, child, _), Tj, qj in zip(edges, T, q):
        tf = TransformStamped()
        tf.header.stamp = stamp
        tf.header.frame_id = parent
        tf.child_frame_id = child
        tr, r = tf.transform.translation, tf.transform.rotation
        tr.x, tr.y, tr.z = (float(v) for v in Tj[:3, 3])
        r.w, r.x, r.y, r.z = (float(v) for v in qj)
        out.append(tf)
    return out


class RobotTf:
    """Publishes the static tree once and the robot's moving links on request (module docstring)."""

    def __init__(self, node, live, world_frame: str, sim_frame: str, publish_robot: bool = True) -> None:
        self.node, self.live = node, live
        self.world_frame, self.sim_frame = world_frame, sim_frame
        self.publish_robot = bool(publish_robot)
        robot = live.robot
        self.frames = RobotFrames(robot.urdf)
        self.base_link = robot.base_link
        self.names = list(live.required_joints)
        self._last_stamp: Optional[int] = None
        self.pub_tf = node.create_publisher(TFMessage, "/tf", 100)
        self.pub_tf_static = node.create_publisher(TFMessage, "/tf_static", LATCHED_QOS)
        self.pub_description = None
        if self.publish_robot:
            self.pub_description = node.create_publisher(String, "/robot_description", LATCHED_QOS)
            self.pub_description.publish(String(data=robot_description(robot.config.urdf)))
        self.publish_static()

    def static_transforms(self) -> list[tuple[str, str, np.ndarray]]:
        """(parent, child, T [4, 4]) of everything that does not move; world -> sim first."""
        sim3 = self.live.base_to_sim
        M = np.asarray(sim3.matrix(), dtype=np.float64)
        scale = float(np.cbrt(np.linalg.det(M[:3, :3])))
        T_world_base = M.copy()
        T_world_base[:3, :3] /= scale
        if abs(scale - 1.0) > 1e-6:
            self.node.get_logger().warn(
                f"the scene's robot -> simulation transform has scale {scale:.6f}: TF carries no scale, so the "
                f"robot links on /tf are placed by its rotation and translation only")
        out = [(self.world_frame, self.sim_frame, np.eye(4))]
        if self.publish_robot:
            out.append((self.world_frame, self.base_link, T_world_base))
            out += self.frames.static_transforms()
        for c in self.live.cameras:
            child = camera_frame_id(self.sim_frame, c.name)
            if c.cam_to_sim is not None:
                out.append((self.world_frame, child, np.asarray(c.cam_to_sim, dtype=np.float64)))
            else:
                out.append((c.mount_link, child, np.asarray(c.link_to_cam, dtype=np.float64)))
        return out

    def publish_static(self) -> None:
        stamp = self.node.get_clock().now().to_msg()
        self.pub_tf_static.publish(TFMessage(transforms=[matrix_to_tf(T, p, c, stamp)
                                                         for p, c, T in self.static_transforms()]))

    def publish(self, joint_vec: Optional[np.ndarray], stamp_ns: int) -> bool:
        """The moving links for `joint_vec` (``live.required_joints`` order) at `stamp_ns`;
        nothing without a joint state, a second time for the same stamp, or with the robot off."""
        if not self.publish_robot or joint_vec is None or stamp_ns == self._last_stamp:
            return False
        stamp = stamp_from_ns(stamp_ns)
        self.pub_tf.publish(TFMessage(transforms=_transforms(self.frames.moving_transforms(self.names, joint_vec), stamp)))
        self._last_stamp = stamp_ns
        return True
