"""What happens to a frame at run time, free of ROS.

``pairing`` (image and detections matched by stamp) -> ``crops`` (one square crop per
box) -> ``state_bank`` (each track's recurrent state and filter row) -> the model
backend's step -> ``intent_filter`` (hold through blinks) -> ``results``. ``engine``
runs that chain once per frame; ``worker`` (drop-oldest queue and thread) and ``stats``
(latency window, diagnostics status) are what a live adapter wraps around it.
"""
