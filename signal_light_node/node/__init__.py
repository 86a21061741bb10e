"""The ROS 2 adapter of signal_light_node: parameters, stamp pairing, the work queue and the node.

``params``, ``pairing`` and ``worker`` are plain Python (rclpy is imported only inside the
functions that declare parameters on a node), so they are tested without a ROS graph;
``detector_node`` is the rclpy node itself.
"""
