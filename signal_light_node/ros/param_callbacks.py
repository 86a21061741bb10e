"""The detector node's parameter callbacks: a change is checked, then applied.

:class:`ParameterCallbacks` is the part of the node
(:class:`~signal_light_node.ros.detector_node.SignalLightDetector`) that answers ``ros2 param
set``: a change is refused with the reason when the parameters it would give are
invalid (:func:`~signal_light_node.ros.params.updated`; the read-only ones are refused
there too), else it replaces the node's ``params`` and the pairing takes the new slop and
timeout.
"""

from __future__ import annotations

from typing import Any, List

from rcl_interfaces.msg import SetParametersResult

from signal_light_node.errors import ConfigError
from signal_light_node.ros.params import updated


class ParameterCallbacks:
    """Checking and applying parameter changes (a part of ``SignalLightDetector``).

    Uses the node's ``params``, ``_pairer`` and ``_param_callbacks``.
    """

    def _watch_parameters(self) -> None:
        """Register the callbacks (once; ``configure`` may run again after cleanup)."""
        if not self._param_callbacks:
            self.add_on_set_parameters_callback(self._check_new_parameters)
            self.add_post_set_parameters_callback(self._apply_new_parameters)
            self._param_callbacks = True

    def _check_new_parameters(self, changes: List[Any]) -> SetParametersResult:
        try:
            updated(self.params, {c.name: c.value for c in changes})
        except ConfigError as exc:
            return SetParametersResult(successful=False, reason=str(exc))
        return SetParametersResult(successful=True)

    def _apply_new_parameters(self, changes: List[Any]) -> None:
        self.params = updated(self.params, {c.name: c.value for c in changes})
        self._pairer.configure(*self.params.pairing_ns)
        self.get_logger().info("parameters changed: " + ", ".join(
            f"{c.name}={c.value}" for c in changes))
