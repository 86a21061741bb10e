"""Shared pytest fixtures; keep them small and generic."""

from __future__ import annotations

import os
import random
from pathlib import Path
from typing import Callable, Dict

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="session")
def repo_root() -> Path:
    """The repository's top directory."""
    return REPO_ROOT


def isolated_ros_env(domain_id: int | None = None) -> Dict[str, str]:
    """A copy of ``os.environ`` for an rclpy subprocess that sees only its own peers.

    A random ``ROS_DOMAIN_ID`` (0..101, the range valid on every platform) keeps
    concurrent test runs apart; discovery stays on this machine.
    """
    env = dict(os.environ)
    env["ROS_DOMAIN_ID"] = str(random.SystemRandom().randint(0, 101)
                               if domain_id is None else domain_id)
    env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    env.pop("ROS_STATIC_PEERS", None)
    env["PYTHONUNBUFFERED"] = "1"
    return env


@pytest.fixture()
def rclpy_isolated_env() -> Callable[..., Dict[str, str]]:
    """Factory of subprocess environments; every call of one test shares one random domain.

    Usage: ``env = rclpy_isolated_env()``, then ``subprocess.Popen(..., env=env)``.
    """
    domain = random.SystemRandom().randint(0, 101)
    return lambda: isolated_ros_env(domain)


@pytest.fixture()
def one_torch_thread():
    """Run the test with one torch thread (results that depend on the thread count's
    rounding stay comparable), restoring the count after."""
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)
