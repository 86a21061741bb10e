"""Join checkpoints of one recipe, trained apart with different seeds over the same frozen
trunk, into one model that averages them (``model.trunk_ensemble``).

    python -m signal_light_node.training.join_members --member RUN_S1/trunk/best.pt \\
        --member RUN_S2/trunk/best.pt --out RUN/joined.pt

The members must be the same model (config equal but for the temperatures) on the same
trunk weights; the first difference is named and nothing is written. The members'
temperatures are dropped: fit the joined model's with ``training.calibrate``.
"""

from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence

import torch

from signal_light_node.errors import CheckpointError
from signal_light_node.model.checkpoint import (FILE_META, LoadedModel, load_checkpoint,
                                                save_checkpoint)
from signal_light_node.model.registry import build_model
from signal_light_node.model.trunk_ensemble import member_config

#: Metadata of each member kept in the joined file's ``meta["members"]``.
MEMBER_META = ("validation", "step", "args", "created")


def _check_same_model(paths: Sequence[Path], loaded: Sequence[LoadedModel]) -> None:
    """Raise unless every member is one model of the same config on the same trunk."""
    first = loaded[0]
    if first.config.encoder == "cnn" or first.config.members != 1:
        raise CheckpointError(f"{paths[0]}: only single trunk-encoder models can be joined "
                              f"(encoder {first.config.encoder}, members {first.config.members})")
    want = member_config(first.config).to_dict()
    trunk = first.model.trunk.state_dict()
    for path, other in zip(paths[1:], loaded[1:]):
        theirs = member_config(other.config).to_dict() if other.config.members == 1 else None
        if theirs != want:
            diff = "members" if theirs is None else \
                next(k for k in want if want[k] != theirs.get(k))
            raise CheckpointError(f"{path}: config differs from {paths[0]}'s in {diff!r}; "
                                  f"members must be one model")
        for name, value in other.model.trunk.state_dict().items():
            if not torch.equal(value, trunk[name]):
                raise CheckpointError(f"{path}: trunk weight {name!r} differs from {paths[0]}'s; "
                                      f"members must share one trunk")


def join_members(paths: Sequence[Path], out: Path) -> Path:
    """Write the model averaging the checkpoints ``paths`` to ``out``.

    Raises:
        CheckpointError: Fewer than two members, or they are not one model on one trunk.
    """
    if len(paths) < 2:
        raise CheckpointError(f"joining needs at least two members, got {len(paths)}")
    loaded = [load_checkpoint(p) for p in paths]
    _check_same_model(paths, loaded)
    config = member_config(loaded[0].config).replace(members=len(paths))
    model = build_model(config)
    model.trunk.load_state_dict(loaded[0].model.trunk.state_dict())
    for target, source in zip(model.members, loaded):
        state = {k: v for k, v in source.model.state_dict().items() if not k.startswith("trunk.")}
        target.load_state_dict(state)
    # What the members share (the recipe, training data, trunk weights) stays on top.
    meta: Dict[str, Any] = {k: v for k, v in loaded[0].meta.items()
                            if k not in FILE_META + MEMBER_META + ("calibration",)}
    data = [m.meta.get("training_data") for m in loaded]
    if any(d != data[0] for d in data):
        meta["training_data"] = data
    meta["members"] = [dict({k: m.meta[k] for k in MEMBER_META if k in m.meta}, path=str(p))
                       for p, m in zip(paths, loaded)]
    return save_checkpoint(out, model.eval(), config, meta)


def main(argv: Optional[List[str]] = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--member", type=Path, action="append", required=True,
                        help="a member checkpoint (twice or more)")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    path = join_members(args.member, args.out)
    print(json.dumps({"out": str(path), "members": [str(p) for p in args.member]}))
    return 0


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
