"""The ROS 2 adapter of signal_light_node and the live-graph tools around it.

Plain Python, testable without a ROS graph: ``params`` (every node parameter, its
descriptor and validation; rclpy is imported only inside the functions that declare them),
``pairing`` (image/detections pairing by stamp), ``worker`` (drop-oldest work queue and
its thread), ``stats`` (latency window and the diagnostics status) and ``bag_player``
(what ``signal-light play`` publishes and when).

rclpy: ``detector_node`` (the ``signal_light_detector`` node, executable ``detector``),
``ros_io`` (QoS, message classes, signal handling shared by the commands) and ``drain``
(waits until a running detector has finished its frames; used by the demo).
"""
