"""The ROS 2 adapter: the only package that imports rclpy or generated message modules.

``detector_node`` (the ``signal_light_detector`` node, executable ``detector``: its
parameters, cameras and inputs) with its parts ``node_lifecycle`` (configure, activate,
deactivate, cleanup, the run loop), ``frame_path`` (the worker: decode, engine, outputs),
``diagnostics`` (``/diagnostics``) and ``param_callbacks`` (parameter changes), ``cameras``
(each camera's pairing, topics and figures), ``lifecycle_node`` (its managed variant,
executable ``detector_lifecycle``),
``params`` (every node parameter, its descriptor and validation), ``messages`` (rclpy
message classes and factory), ``ros_io`` (QoS, contexts, signal handling shared by the
tools), ``play`` / ``record`` / ``bag_player`` (``signal-light play`` and ``record``),
``drain`` (waits until a running detector has finished its frames; used by the demo) and
``gaps`` (publisher sequence numbers -> frames lost before the node). A test
(``test/test_architecture.py``) keeps rclpy out of every other package.
"""
