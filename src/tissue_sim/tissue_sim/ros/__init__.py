"""ROS helpers for the nodes: topic names, QoS profiles, parameter declaration, spin."""
