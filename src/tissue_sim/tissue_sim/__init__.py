"""tissue_sim: human motion with soft-tissue deformation (Inaba et al. 2005), as a ROS 2 service.

``tissue_sim.core`` is the ROS-free physics core (model building, solver, analysis); it imports
numpy, numba and trimesh, never rclpy. ``tissue_sim.nodes`` are thin rclpy layers over it.
"""
__version__ = '0.1.0'
