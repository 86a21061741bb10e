"""The node harness itself: a node that ignores Ctrl-C is stopped, and its log then says
where every thread was (faulthandler on SIGABRT), so a hang at shutdown explains itself."""

from __future__ import annotations

import os
import sys
from pathlib import Path

from node_harness import DetectorProcess

_DEAF = """import signal, time
signal.signal(signal.SIGINT, signal.SIG_IGN)
print("up", flush=True)
def wait_here():
    time.sleep(60)
wait_here()
"""


def _deaf_node(tmp_path: Path) -> Path:
    script = tmp_path / "deaf_node"
    script.write_text(f"#!{sys.executable}\n{_DEAF}")
    script.chmod(0o755)
    return script


def test_a_node_deaf_to_ctrl_c_is_stopped_and_leaves_its_stacks(tmp_path: Path) -> None:
    node = DetectorProcess([], dict(os.environ), tmp_path / "deaf.log",
                           executable=str(_deaf_node(tmp_path)))
    node.wait_ready(timeout=30.0, line="up")
    code = node.stop(timeout=1.0)
    assert code != 0 and node.proc.poll() is not None
    assert "wait_here" in node.text()  # the hung frame, from faulthandler's dump
