"""Training of the light-state model: data sources, balanced sampling and the loop.

* :mod:`.sources` turns labelled bags, the UC Merced rear-signal layout and
  materialised synthetic splits into per-track sequences (:class:`TrackSequence`) and
  serves training windows from them.
* :mod:`.sampling` assigns a window its rarity stratum (HAZARD, brake with a blinker,
  a blinker, brake, nothing) and balances what the trainer sees.
* :mod:`.train` is the loop behind ``signal-light train`` (single process or DDP).
"""
