"""Command-line options that several ``signal-light`` commands share.

One definition each, so that ``train``, ``evaluate`` and ``replay`` spell, default and
explain them alike. Every helper takes an ``argparse`` parser or argument group.
"""

from __future__ import annotations

import argparse
from pathlib import Path

# The common base of ArgumentParser and argument groups (what add_argument lives on).
ArgumentContainer = argparse._ActionsContainer


def add_labelled_data_options(group: ArgumentContainer) -> None:
    """``--bags`` and ``--ucm``: labelled data (both lists of paths, empty by default)."""
    group.add_argument("--bags", nargs="+", type=Path, default=[], metavar="BAG",
                       help="labelled bags (/ground_truth/vehicle_lights + images + detections)")
    group.add_argument("--ucm", nargs="+", type=Path, default=[], metavar="ROOT",
                       help="UC Merced Vehicle Rear Signal dataset roots")


def add_torch_options(group: ArgumentContainer) -> None:
    """``--device``, ``--threads`` and ``--no-progress`` of the commands that run the model."""
    group.add_argument("--device", default="cpu", help="torch device: cpu, cuda or cuda:N")
    group.add_argument("--threads", type=int, default=None,
                       help="torch CPU threads (unset: torch's choice)")
    group.add_argument("--no-progress", action="store_true", help="no progress bars")
