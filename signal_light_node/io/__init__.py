"""Bags, images and messages, without rclpy.

``bagio`` (rosbag2 / MCAP reading and writing with rosbags), ``mcap_recovery``
(reading a cut MCAP file without its index, for ``bagio``), ``image_codec``
(Image / CompressedImage <-> BGR arrays), ``conversions`` (messages <-> boxes and
results, for any message factory) and ``topics`` (every topic and type name).
"""
