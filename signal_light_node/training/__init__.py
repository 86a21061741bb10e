"""Training of the light-state model: data sources, balanced sampling and the loop.

* :mod:`.sources` turns labelled bags, the UC Merced rear-signal layout and
  materialised synthetic splits into per-track sequences (:class:`TrackSequence`) and
  serves training windows from them.
* :mod:`.sampling` assigns a window its rarity stratum (HAZARD, brake with a blinker,
  a blinker, brake, nothing) and balances what the trainer sees.
* :mod:`.track_batches` cuts in-memory tracks into single-frame batches or stateful
  lanes (the recipe of the shipped weights).
* ``signal-light train`` (single process or DDP), by concern: :mod:`.options` (the
  options and their defaults), :mod:`.loop` (the :class:`Trainer` and its steps),
  :mod:`.run_model` (fresh, warm-started or resumed model), :mod:`.loss`,
  :mod:`.optimizer`, :mod:`.schedule` (plateau drops, final cosine), :mod:`.precision`
  (bf16 autocast), :mod:`.run_data` (tracks, held-out tracks, validation items),
  :mod:`.loaders` (the training DataLoader per ``--mode``), :mod:`.streams` (replay,
  thinning, mixing of the synthetic stream), :mod:`.augment`, :mod:`.model_inputs`
  (float crops, the lanes' carried state), :mod:`.validation`, :mod:`.checkpointing`
  (checkpoint metadata, the resumable training state), :mod:`.progress` (running figures,
  progress bar, ``log.jsonl``), :mod:`.seeding` and :mod:`.distributed`.
"""

#: How training batches are cut (``signal-light train --mode``; see ``TrainOptions.mode``).
BATCH_MODES = ("windows", "frames", "lanes")

#: ``signal-light train --frame-targets``: which label array of a split the per-frame
#: stage learns (``TrainOptions.frame_targets``; see ``data.stream`` for ``lit_labels``).
FRAME_TARGETS = {"state": "labels", "lit": "lit_labels"}
#: ``signal-light train --precision``: float32, the forward pass autocast to bfloat16, or
#: "auto" (bfloat16 where the hardware runs it natively; ``precision.resolve_precision``).
PRECISIONS = ("fp32", "bf16", "auto")
