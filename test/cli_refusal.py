"""A ``signal-light`` command refused: exit status 2, one line on stderr, nothing written."""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

from signal_light_node.cli import main


def refused(capsys, command: str, args: Sequence[object], out: Path,
            extra: Sequence[str] = ()) -> str:
    """Run ``signal-light COMMAND ARGS --out OUT EXTRA``; assert it was refused in one line
    and wrote nothing at ``out`` (nor beside it); return the message."""
    assert main([command, *map(str, args), "--out", str(out), *extra]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"signal-light {command}: error:") and "\n" not in err
    assert not out.exists() and not list(out.parent.glob(out.name + "*"))
    return err
