"""ROS helpers: numpy CDR encoders for big messages, QoS profiles, parameter helpers."""
