"""Training and evaluation data made from the synthetic scene renderer.

``stream.SyntheticSequenceStream`` renders sequences of per-track crops on the fly for
training; ``split.write_split`` / ``split.SequenceSplit`` materialise a fixed split on disk
for validation and testing. Both crop with ``signal_light_node.runtime.crops``, as the node does.
"""

from signal_light_node.data.stream import SyntheticSequenceStream, collate_sequences

__all__ = ["SyntheticSequenceStream", "collate_sequences"]
