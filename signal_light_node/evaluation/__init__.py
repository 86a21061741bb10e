"""Evaluation: what is scored and how, below both ``training/`` and ``tools/``.

* ``tracks``: :class:`~.tracks.TrackSequence`, one vehicle track (crops, labels, stamps,
  groups), and ``track_from_item`` (a stream or split item as a track).
* ``metrics``: per-frame metrics of the heads (accuracy, macro recall/F1, FP/FN rates,
  confusion matrices, breakdowns, switches), pure numpy.
* ``scoring``: ``TrackScorer`` and ``EvalSettings``, the warm-up and grace-window rules.
* ``streaming``: ``evaluate_tracks`` / ``predict_track_batch``, a model stepped through
  tracks frame by frame as the engine steps it (``signal-light evaluate``).
* ``ideal_observer``: the ceiling of every metric on a split (``--ideal-observer``).

Nothing here imports ``training``, ``tools``, ``commands`` or ``ros``
(``test/test_architecture.py`` checks the layers). Nothing is imported here either: each
module is imported on its own (``streaming`` loads torch, ``metrics`` only numpy).
"""
