"""signal_light_node: online vehicle light-state perception for ROS 2 Jazzy.

Folders follow a frame: ``io/`` (bags, images, messages) -> ``runtime/`` (pairing, crops,
state bank, engine, intent filter) -> ``model/`` (config, network, checkpoints). Around
them: ``synth/`` and ``evalgen/`` (scene generators), ``data/`` and ``training/``,
``tools/`` (replay, metrics, demo report, overlays), ``commands/`` (the ``signal-light``
CLI) and ``ros/``, the ROS 2 adapter and the only package that imports rclpy.
"""

import os

# torch's OpenMP threads spin while idle by default; on a small shared CPU (the node's worker,
# rclpy's executor and the camera driver all compete) that made a 32-track step 15x slower.
# It only takes effect before torch is first imported, hence here. Callers can still override it.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

__version__ = "0.1.0"
