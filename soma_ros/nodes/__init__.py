"""The thin rclpy layer of soma_ros: message conversions, QoS, the nodes."""
