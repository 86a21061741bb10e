#!/usr/bin/env python3
"""Per track of a bag: a light published ON as recorded, and on its looks held still.

Every ``--every``-th crop of each track is repeated for the track's length and run through
the model and the node's filter (``evaluation.still_looks``). A look read ON held still is
an absolute read (the look alone passes for the light); a track published ON as recorded
whose looks are not is read from the changes between its frames. Seconds per checkpoint on
the committed night bags (docs/model.md, "Which of the truck's looks read braking").
Usage::

    python scripts/probe_still_looks.py --bag bags/night_tail_lamps \\
        --checkpoint signal_light_node/weights/default.pt --checkpoint runs/fillg/default.pt
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch

from signal_light_node.evaluation.still_looks import on_share, still_look_reads
from signal_light_node.evaluation.streaming import predict_track_probs
from signal_light_node.labels import LIGHT_TASKS, TASKS
from signal_light_node.model.checkpoint import load_checkpoint
from signal_light_node.training.sources import load_bag_tracks


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--bag", type=Path, required=True, help="a bag with detections")
    parser.add_argument("--checkpoint", action="append", required=True, help="repeatable")
    parser.add_argument("--task", default="brake", choices=LIGHT_TASKS)
    parser.add_argument("--every", type=int, default=3, help="take every n-th look")
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    column = TASKS.index(args.task)
    for path in args.checkpoint:
        model = load_checkpoint(path, map_location="cpu").model.eval()
        print(path)
        for track in load_bag_tracks(args.bag, model.config.crop_config()):
            with torch.no_grad():
                recorded = predict_track_probs(model, [track])[0][0][:, column]
                reads = still_look_reads(model, track, args.task, args.every)
            marks = "".join("1" if r else "0" for r in reads)
            print(f"  {track.track_id:24s} {args.task} ON as recorded "
                  f"{100 * on_share(recorded):5.1f} % of judged frames; looks read ON held "
                  f"still {sum(reads):3d} of {len(reads):3d}: {marks}")


if __name__ == "__main__":
    main()
