"""SequenceGaps: lost messages from publication sequence numbers."""

from signal_light_node.ros.gaps import SequenceGaps


def test_gaps_of_one_publisher_are_counted():
    gaps = SequenceGaps()
    assert [gaps.add(s) for s in (5, 6, 9, 10, 20)] == [0, 0, 2, 0, 9]
    assert gaps.lost == 11 and gaps.supported


def test_two_interleaved_publishers_and_a_restart_count_no_false_gaps():
    gaps = SequenceGaps()
    for seq in (100, 5, 101, 6, 102, 7, 1, 2, 103, 3):  # 1.. = a restarted publisher
        gaps.add(seq)
    assert gaps.lost == 0
    gaps.add(105)  # 104 of the first publisher lost
    assert gaps.lost == 1


def test_no_sequence_numbers_means_unsupported():
    gaps = SequenceGaps()
    assert gaps.add(None) == 0 and gaps.add(0) == 0
    assert gaps.supported is False and gaps.lost == 0


def test_streams_are_bounded():
    gaps = SequenceGaps(max_streams=2)
    for seq in (300, 200, 100):  # three publishers; the first is forgotten
        gaps.add(seq)
    assert gaps.add(301) == 100  # continues the 200 stream now: 301 - 200 - 1


def test_a_late_message_fills_its_gap_instead_of_counting_twice():
    gaps = SequenceGaps()
    for seq in (1, 2, 5):  # 3 and 4 missing ...
        gaps.add(seq)
    assert gaps.lost == 2
    assert gaps.add(4) == -1 and gaps.lost == 1  # ... until 4 comes late (reliable repair)
    assert gaps.add(6) == 0 and gaps.add(3) == -1 and gaps.lost == 0
    assert gaps.add(3) == 0 and gaps.lost == 0  # a repeat is not a gap filled twice
