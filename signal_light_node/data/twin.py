"""A split's twin: the same scenes drawn in another style family.

The renderer draws a scene's style family (lamp colours, camera tone; ``synth.lamps``)
from a random stream of its own, so a split rendered again with the same seed and options
but another ``family`` holds the same scenes, vehicles, tracks, boxes and labels; only the
pixels differ. Scoring a model on a held-out-family split and on its twin in the training
families separates what the style costs from what the scenes cost (a split is a sample of
a few dozen whole scenes, so two splits of one distribution differ).

From the shell::

    python -m signal_light_node.data.twin runs/data/family_test_split runs/twins/family_test_own
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path
from typing import Any, List, Optional

from signal_light_node.data.split import SequenceSplit, write_and_summarise, write_split
from signal_light_node.errors import ConfigError
from signal_light_node.synth.lamps import STYLE_FAMILIES


def _tuples(value: Any) -> Any:
    """JSON lists back to the tuples the stream's options were given as."""
    if isinstance(value, list):
        return tuple(_tuples(v) for v in value)
    if isinstance(value, dict):
        return {k: _tuples(v) for k, v in value.items()}
    return value


def write_twin(split_dir: "str | os.PathLike[str]", out_dir: "str | os.PathLike[str]", *,
               family: Optional[int] = None, overwrite: bool = False,
               progress: bool = True) -> Path:
    """Render ``split_dir``'s split again in style family ``family``.

    Args:
        split_dir: A split written by :func:`~signal_light_node.data.split.write_split`.
        out_dir: Directory of the twin.
        family: One of ``synth.lamps.STYLE_FAMILIES``, or None for the training families
            (drawn per scene, as training renders are).
        overwrite: Replace an existing split in ``out_dir``.
        progress: Show a progress bar.

    Returns:
        The twin's manifest path.

    Raises:
        ConfigError: An unknown family, or a twin in the split's own family.
        SignalLightError: ``split_dir`` is not a split.
    """
    if family is not None and family not in STYLE_FAMILIES:
        raise ConfigError(f"family must be one of {STYLE_FAMILIES} or None, got {family!r}")
    split = SequenceSplit(split_dir)
    manifest = split.manifest
    stream = _tuples(dict(manifest.get("stream", {})))
    overrides = dict(stream.pop("renderer_overrides", {}))
    if overrides.get("family") == family:
        what = "the training families" if family is None else f"family {family}"
        raise ConfigError(f"{split_dir} is already drawn in {what}; a twin needs another "
                          "family (--family)")
    overrides.pop("family", None)
    if family is not None:
        overrides["family"] = family
    return write_split(out_dir, seed=manifest["seed"], n_sequences=len(split),
                       seq_len=split.seq_len, crop=split.crop,
                       full_tracks=manifest["full_tracks"], overwrite=overwrite,
                       progress=progress, **stream,
                       **({"renderer_overrides": overrides} if overrides else {}))


def main(argv: Optional[List[str]] = None) -> int:
    """Write a twin from the command line (``python -m signal_light_node.data.twin``)."""
    parser = argparse.ArgumentParser(prog="python -m signal_light_node.data.twin",
                                     description="a split's scenes in another style family")
    parser.add_argument("split", help="the split to copy the scenes of")
    parser.add_argument("out", help="directory to write")
    parser.add_argument("--family", type=int, default=None,
                        help="style family of the twin (default: the training families)")
    parser.add_argument("--overwrite", action="store_true")
    args = parser.parse_args(argv)
    return write_and_summarise(lambda: write_twin(args.split, args.out, family=args.family,
                                                  overwrite=args.overwrite))


if __name__ == "__main__":
    sys.exit(main())
