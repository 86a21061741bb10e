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


#: Every domain ID valid on every platform (0..101), in one random order per test session.
_DOMAINS = random.SystemRandom().sample(range(102), 102)
_handed_out = 0


def fresh_domain_id() -> int:
    """A ``ROS_DOMAIN_ID`` this test session has not handed out in its last 101 calls.

    Random IDs per call met now and then: a module-scoped node and a test's own node on one
    domain see each other's topics and /diagnostics, and their books mix (a CI run failed on
    it). Walking one random permutation keeps the nodes of one session apart for certain and
    concurrent sessions apart by chance.
    """
    global _handed_out
    domain = _DOMAINS[_handed_out % len(_DOMAINS)]
    _handed_out += 1
    return domain


def isolated_ros_env(domain_id: int | None = None) -> Dict[str, str]:
    """A copy of ``os.environ`` for an rclpy subprocess that sees only its own peers.

    Args:
        domain_id: The ``ROS_DOMAIN_ID``; None: a :func:`fresh_domain_id`. Discovery stays
            on this machine.
    """
    env = dict(os.environ)
    env["ROS_DOMAIN_ID"] = str(fresh_domain_id() if domain_id is None else domain_id)
    env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    env.pop("ROS_STATIC_PEERS", None)
    env["PYTHONUNBUFFERED"] = "1"
    return env


@pytest.fixture()
def rclpy_isolated_env() -> Callable[..., Dict[str, str]]:
    """Factory of subprocess environments; every call of one test shares one fresh domain.

    Usage: ``env = rclpy_isolated_env()``, then ``subprocess.Popen(..., env=env)``.
    """
    domain = fresh_domain_id()
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
