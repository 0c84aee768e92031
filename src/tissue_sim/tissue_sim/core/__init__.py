"""ROS-free core of tissue_sim. Never import rclpy (or anything ROS) from this package."""
