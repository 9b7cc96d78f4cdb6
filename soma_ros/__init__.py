"""soma_ros: a ROS 2 node suite serving a learned real-to-sim simulator of
robotic soft-body manipulation (the SoMA method).

Layout:
  soma_ros.core      pure torch/numpy (never imports rclpy)
  soma_ros.world     the MuJoCo reference world that records rosbags
  soma_ros.nodes     the thin rclpy layer (live simulator node, bag player)
  soma_ros.commands  the `soma` CLI subcommands
"""

__version__ = "0.1.0"
