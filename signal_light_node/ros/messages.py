"""rclpy message classes and a message factory for them, resolved by type name.

The core builds every message through a factory ``make(msgtype, **fields)``
(:mod:`signal_light_node.io.conversions`); this is the one for rclpy. The generated
``<pkg>.msg`` modules are imported here, lazily, so that nothing outside ``ros/`` does.
"""

from __future__ import annotations

import functools
import importlib
from typing import Any


@functools.lru_cache(maxsize=None)
def rclpy_class(msgtype: str) -> type:
    """The generated rclpy message class of a type, its ``<pkg>.msg`` module imported lazily.

    Cached: the node builds several messages per vehicle and frame with :func:`rclpy_make`.

    Args:
        msgtype: ``pkg/msg/Name`` or ``pkg/Name``.

    Returns:
        The message class.
    """
    parts = msgtype.split("/")
    package, name = parts[0], parts[-1]
    return getattr(importlib.import_module(f"{package}.msg"), name)


def rclpy_make(msgtype: str, **fields: Any) -> Any:
    """Message factory for rclpy (see :func:`rclpy_class`).

    Args:
        msgtype: ``pkg/msg/Name`` or ``pkg/Name``.
        **fields: Field values; omitted fields keep the message defaults.

    Returns:
        An instance of the generated rclpy message class.
    """
    return rclpy_class(msgtype)(**fields)
