"""signal_light_node: online vehicle light-state perception for ROS 2 Jazzy.

The package is split into a core that never imports rclpy (labels, crops, bag I/O,
synthetic data, model, engine, metrics) and a thin ROS adapter in ``node/``.
"""

__version__ = "0.1.0"
