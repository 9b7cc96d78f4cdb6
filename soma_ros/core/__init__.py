"""Pure torch/numpy core of soma_ros. Nothing under this package imports rclpy."""
