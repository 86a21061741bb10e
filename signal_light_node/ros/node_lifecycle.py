"""The detector node's life: configure, activate, deactivate, clean up, and the run loop.

:class:`NodeLifecycle` is the part of the node
(:class:`~signal_light_node.ros.detector_node.SignalLightDetector`) that starts and stops
it. The plain node runs ``configure`` + ``activate`` at start (``setup``); the lifecycle
variant (:mod:`signal_light_node.ros.lifecycle_node`) calls the same steps from its
transitions:

* configure: load and check the model, build the engine, each camera's pairing and the
  work queue;
* activate: create each camera's publishers (one per output adapter), the worker
  (:mod:`signal_light_node.ros.frame_path`), the subscriptions and the diagnostics timer;
* deactivate: stop the worker (queued frames are dropped and counted) and remove the
  topics; the track states, the pairing and the counters are kept;
* cleanup: free the model and the track states.

:func:`run_detector` is the one run loop of ``detector`` and ``detector_lifecycle``.
"""

from __future__ import annotations

import logging
import re
import sys
from typing import TYPE_CHECKING, Any, Callable, List, Optional

import rclpy
from rclpy.executors import ExternalShutdownException
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy_impl
from rclpy.node import Node

from signal_light_node.errors import ConfigError, SignalLightError
from signal_light_node.io.topics import DIAGNOSTICS_TOPIC, DIAGNOSTICS_TYPE
from signal_light_node.outputs import output_adapters
from signal_light_node.ros.cameras import CameraIO, PairerGroup
from signal_light_node.ros.frame_path import decoder_for
from signal_light_node.ros.params import NODE_NAME, foreign_params_file, params_file_paths
from signal_light_node.ros.ros_io import message_class
from signal_light_node.runtime.camera_queue import CameraQueue
from signal_light_node.runtime.pairing import StampPairer
from signal_light_node.runtime.worker import DropOldestQueue, Worker

if TYPE_CHECKING:
    from signal_light_node.ros.detector_node import SignalLightDetector


class NodeLifecycle:
    """Start-up and shut-down of the detector node (a part of ``SignalLightDetector``).

    Uses the node's ``params``, ``_cameras``, ``_several``, ``_subscribe`` and the other
    parts' entry points (``_process_tick`` / ``_process_pair``, ``_snapshot`` and
    ``_publish_diagnostics``, ``_watch_parameters``); sets ``engine``, ``model_path``,
    ``_pairer``, ``_queue``, ``_decode``, ``_worker``, ``_diag`` and ``_timer``.
    """

    def setup(self) -> None:
        """Load the model and start the topics, the worker and the diagnostics timer.

        Raises:
            CheckpointError: The model file is missing or incompatible.
            ConfigError: The model does not fit the parameters (device, crop size).
        """
        self.configure()
        self.activate()

    def configure(self) -> None:
        """Load and check the model and build the engine and the pairing (no topics yet).

        Raises:
            CheckpointError: The model file is missing or incompatible.
            ConfigError: The model does not fit the parameters (device, crop size).
        """
        from signal_light_node.runtime.engine import engine_from_checkpoint

        p = self.params
        self.engine = engine_from_checkpoint(
            p.model_path or None, device=p.device, backend=p.backend, threads=p.num_threads,
            precision=p.precision,
            thresholds=p.thresholds,
            track_timeout_s=p.track_timeout_s, max_tracks=p.max_tracks, max_gap_s=p.max_gap_s,
            intent_filter=p.intent_filter_config,
            max_boxes=p.max_boxes_per_frame)
        self.model_path = self.engine.backend.source
        for camera in self._cameras:
            camera.pairer = StampPairer(*p.pairing_ns, p.image_queue_size,
                                        p.detection_queue_size)
        self._pairer = PairerGroup([c.pairer for c in self._cameras]) if self._several \
            else self._cameras[0].pairer
        self._queue = self._new_queue()
        self._decode = decoder_for(p.image_transport)
        self._watch_parameters()
        self.get_logger().info(
            f"model {self.model_path} ({self._backend_text()}) on {p.device}; crop margin "
            f"{self.engine.crop.margin:g} (the model checkpoint's)")

    def activate(self) -> None:
        """Create the publishers, the worker, the subscriptions and the diagnostics timer."""
        p = self.params
        if self._queue.closed:  # a worker stopped by deactivate closed it; keep its count
            self._dropped_before += self._queue.dropped
            for camera in self._cameras:
                camera.dropped_before += self._camera_queue_drops(camera)
            self._queue = self._new_queue()
        for camera in self._cameras:
            self._create_camera_topics(camera)
        self._diag = self._create_publisher(message_class(DIAGNOSTICS_TYPE), DIAGNOSTICS_TOPIC,
                                            10)
        process = self._process_tick if self._several else self._process_pair
        self._worker = Worker(self._queue, process, name="signal_light_inference").start()

        for camera in self._cameras:
            self._subscribe(camera)
        self._last_snapshot = self._snapshot()
        self._timer = self.create_timer(p.diagnostics_period_s, self._publish_diagnostics)
        pairing = 'exact' if p.sync_slop_s == 0 else f'within {p.sync_slop_s} s'
        for camera in self._cameras:
            self.get_logger().info(
                f"{f'camera {camera.name}: ' if camera.name else ''}outputs: "
                f"{', '.join(pub.topic_name for _, pub in camera.outputs)}")
        if not self._several:
            camera = self._cameras[0]
            self.get_logger().info(
                f"ready: {camera.image_topic} ({p.image_transport}, {p.reliability}) + "
                f"{camera.subscriptions[1].topic_name} "
                f"-> {camera.outputs[0][1].topic_name}; model {self.model_path} "
                f"({self._backend_text()}) on {p.device}, pairing {pairing}")
            return
        inputs = "; ".join(f"{c.name}: {c.image_topic} + {c.subscriptions[1].topic_name} -> "
                           f"{c.outputs[0][1].topic_name}" for c in self._cameras)
        self.get_logger().info(
            f"ready: {len(self._cameras)} cameras ({p.image_transport}, {p.reliability}), "
            f"one model step per tick: {inputs}; model {self.model_path} "
            f"({self._backend_text()}) on {p.device}, pairing {pairing}")

    def _backend_text(self) -> str:
        """The backend and weight precision in use, and whether ``auto`` chose them."""
        auto = ", chosen by backend auto" if self.params.backend == "auto" else ""
        return f"{self.engine.backend.name} {self._precision()}{auto}"

    def _precision(self) -> str:
        return str(getattr(self.engine.backend, "precision", "fp32"))

    def _create_publisher(self, msg_type: Any, topic: str, depth: int) -> Any:
        publisher = self.create_publisher(msg_type, topic, depth)
        self._publishers_made.append(publisher)
        return publisher

    def _create_camera_topics(self, camera: CameraIO) -> None:
        """One publisher per output adapter (the result array first; markers and the debug
        image as the parameters ask)."""
        adapters = output_adapters(markers=self.params.publish_markers,
                                   debug_image=self.params.publish_debug_image)
        camera.outputs = [(adapter, self._create_publisher(message_class(adapter.msgtype),
                                                           camera.topic(adapter.node_topic),
                                                           adapter.depth))
                          for adapter in adapters]

    def _new_queue(self) -> Any:
        """The work queue: drop-oldest for one camera, one per camera for several."""
        if self._several:
            return CameraQueue([c.name for c in self._cameras], self.params.work_queue_size)
        return DropOldestQueue(self.params.work_queue_size)

    def _camera_queue_drops(self, camera: CameraIO) -> int:
        """The camera's frames dropped from the current work queue."""
        if isinstance(self._queue, CameraQueue):
            return self._queue.dropped_by_camera.get(camera.name, 0)
        return self._queue.dropped

    def deactivate(self) -> None:
        """Stop taking and publishing frames; the track states and counters are kept.

        Frames still queued are dropped and counted; messages waiting for a partner
        stay in the pairing and expire there as usual.
        """
        self.stop()
        self._worker = None
        for camera in self._cameras:
            for sub in camera.subscriptions:
                self.destroy_subscription(sub)
            camera.subscriptions, camera.outputs = [], []
        if getattr(self, "_timer", None) is not None:
            self.destroy_timer(self._timer)
            self._timer = None
        for pub in self._publishers_made:
            self.destroy_publisher(pub)
        self._publishers_made = []
        self._diag = None

    def cleanup(self) -> None:
        """Free the model and every track state (``configure`` loads them again)."""
        self.engine = None

    def stop(self) -> None:
        """Stop the worker (frames still queued are dropped and counted)."""
        if self._worker is not None:
            self._worker.stop(drain=False, timeout=5.0)


def _init_ros(args: Optional[List[str]]) -> None:
    """``rclpy.init`` with rcl's own error line silenced, so a bad argument is one line.

    Raises:
        ConfigError: The ROS arguments cannot be parsed (bad rule, missing params file...).
    """
    from rclpy.logging import LoggingSeverity, get_logger_level, set_logger_level

    before = get_logger_level("rcl")
    set_logger_level("rcl", LoggingSeverity.FATAL)
    try:
        rclpy.init(args=args)
    except _rclpy_impl.RCLError as exc:
        # rcl appends ", at <source file>:<line>" for every frame; the user needs none.
        text = re.sub(r", at \S+:\d+", "", str(exc).splitlines()[0])
        raise ConfigError(f"bad ROS arguments: {text}") from None
    finally:
        set_logger_level("rcl", before)


def _warn_foreign_params_files(node: Node, args: Optional[List[str]]) -> None:
    for path in params_file_paths(list(sys.argv if args is None else args)):
        problem = foreign_params_file(path, node.get_fully_qualified_name())
        if problem is not None:
            node.get_logger().warning(problem)


def run_detector(make_node: Callable[[], "SignalLightDetector"],
                 start: Callable[["SignalLightDetector"], None],
                 args: Optional[List[str]] = None) -> int:
    """Init ROS, build the node, ``start`` it and spin until Ctrl-C or a shutdown request.

    The one run loop of ``detector`` and ``detector_lifecycle``: any start-up problem (bad
    ROS arguments, parameters, model, device) is reported in ONE log line and gives exit
    code 1; a params file without a section for this node is warned about.

    Args:
        make_node: Builds the node (after ``rclpy.init``).
        start: What to do before spinning (load and activate, or wait for transitions).
        args: ROS arguments; None reads ``sys.argv``.

    Returns:
        The exit code.
    """
    logging.basicConfig(level=logging.INFO, format="[%(levelname)s] [%(name)s]: %(message)s")
    node: Optional[SignalLightDetector] = None
    code = 0
    try:
        _init_ros(args)
        node = make_node()
        _warn_foreign_params_files(node, args)
        start(node)
        _spin(node)
    except SignalLightError as exc:
        logger = node.get_logger() if node is not None else rclpy.logging.get_logger(NODE_NAME)
        logger.fatal(f"cannot start: {exc}")
        code = 1
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        if node is not None:
            node.stop()
            node.destroy_node()
        rclpy.try_shutdown()
    return code


def _spin(node: Node) -> None:
    """``rclpy.spin`` until shutdown; a Ctrl-C that lands between two waits shuts the
    context down under the executor, which then raises rclpy's RCLError ("the given
    context is not valid") instead of ExternalShutdownException: that is a shutdown too."""
    try:
        rclpy.spin(node)
    except Exception:
        if rclpy.ok(context=node.context):
            raise
