"""The managed (lifecycle) variant of the detector, executable ``detector_lifecycle``.

Same node name, parameters, topics and processing as ``detector``; only the start-up is
driven from outside through the lifecycle services (``~/change_state``, ``~/get_state``):

* configure: load and check the model, build the engine and the pairing;
* activate: create the publishers, the subscriptions, the worker and the diagnostics timer;
* deactivate: stop taking frames (queued ones are dropped and counted) and remove the
  topics; the track states, the pairing and the counters are kept;
* cleanup: free the model and the track states;
* shutdown: deactivate and clean up from whichever state the node is in.

A transition that fails (a missing model file, CUDA asked for without it) is logged in
one line and answered FAILURE, leaving the node where it was.
"""

from __future__ import annotations

import sys
from typing import Any, Callable, List, Optional

from rclpy.lifecycle import LifecycleNode, State, TransitionCallbackReturn

from signal_light_node.errors import SignalLightError
from signal_light_node.ros.detector_node import SignalLightDetector
from signal_light_node.ros.node_lifecycle import run_detector


class LifecycleSignalLightDetector(SignalLightDetector, LifecycleNode):
    """The detector as a managed node; starts unconfigured.

    Raises:
        ConfigError: From the constructor, when a parameter is unusable.
    """

    def __init__(self, **kwargs: Any) -> None:
        # SignalLightDetector.__init__ hands on to LifecycleNode.__init__ (cooperative MRO).
        super().__init__(**kwargs)
        self._active = False

    def _transition(self, what: str, step: Callable[[], None]) -> TransitionCallbackReturn:
        try:
            step()
        except SignalLightError as exc:
            self.get_logger().error(f"cannot {what}: {exc}")
            return TransitionCallbackReturn.FAILURE
        return TransitionCallbackReturn.SUCCESS

    def on_configure(self, state: State) -> TransitionCallbackReturn:
        """Load the model (a failure leaves the node unconfigured)."""
        return self._transition("configure", self.configure)

    def on_activate(self, state: State) -> TransitionCallbackReturn:
        """Start the topics and the worker."""
        result = self._transition("activate", self.activate)
        self._active = result == TransitionCallbackReturn.SUCCESS
        return result

    def on_deactivate(self, state: State) -> TransitionCallbackReturn:
        """Stop work; keep the track states."""
        self._active = False
        return self._transition("deactivate", self.deactivate)

    def on_cleanup(self, state: State) -> TransitionCallbackReturn:
        """Free the model and the track states."""
        return self._transition("clean up", self.cleanup)

    def on_shutdown(self, state: State) -> TransitionCallbackReturn:
        """Release everything, from any primary state."""
        if self._active:
            self.deactivate()
            self._active = False
        self.cleanup()
        return TransitionCallbackReturn.SUCCESS

    def on_error(self, state: State) -> TransitionCallbackReturn:
        """After a transition raised: drop the topics and the model, back to unconfigured."""
        self.on_shutdown(state)
        return TransitionCallbackReturn.SUCCESS


def main(args: Optional[List[str]] = None) -> int:
    """Run the lifecycle detector until Ctrl-C or a shutdown request; returns the exit code.

    Bad ROS arguments or parameters stop it at once with one log line and exit code 1;
    everything after that (the model included) is reported by the transitions.
    """
    return run_detector(LifecycleSignalLightDetector, _wait_unconfigured, args)


def _wait_unconfigured(node: SignalLightDetector) -> None:
    node.get_logger().info("unconfigured; waiting for the configure transition")


if __name__ == "__main__":
    sys.exit(main())
