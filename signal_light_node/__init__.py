"""signal_light_node: online vehicle light-state perception for ROS 2 Jazzy.

The package is split into a core that never imports rclpy (labels, crops, bag I/O,
synthetic data, model, engine, metrics) and a thin ROS adapter in ``node/``.
"""

import os

# torch's OpenMP threads spin while idle by default; on a small shared CPU (the node's worker,
# rclpy's executor and the camera driver all compete) that made a 32-track step 15x slower.
# It only takes effect before torch is first imported, hence here. Callers can still override it.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

__version__ = "0.1.0"
