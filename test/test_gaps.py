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


def test_a_publisher_that_came_after_subscribing_is_counted_from_its_first_number():
    """Issue 25: a burst whose first messages were lost before the subscription saw any
    (its reader history replaced them, or discovery had not connected yet)."""
    gaps = SequenceGaps()
    gaps.subscribed(0)
    assert gaps.add(28) == 27 and gaps.add(30) == 1 and gaps.lost == 28
    # A second new publisher: counted from 1 too; its 5 does not fill the first's 1..27.
    assert gaps.add(5) == 4 and gaps.add(6) == 0 and gaps.lost == 32


def test_publishers_running_when_subscribed_start_uncounted():
    gaps = SequenceGaps()
    gaps.subscribed(1)
    assert gaps.publishers_before == 1
    assert gaps.add(5000) == 0  # numbered before we subscribed: not ours
    assert gaps.add(5002) == 1
    assert gaps.add(40) == 39  # a publisher started since (or restarted)
    assert gaps.lost == 40


def test_subscribing_again_forgets_the_streams_but_keeps_the_count():
    gaps = SequenceGaps()
    gaps.subscribed(0)
    for seq in (1, 2, 4):
        gaps.add(seq)
    gaps.subscribed(1)  # deactivated and activated again; the publisher went on meanwhile
    assert gaps.add(90) == 0 and gaps.lost == 1


def test_a_forgotten_stream_may_come_back_uncounted():
    gaps = SequenceGaps(max_streams=2)
    gaps.subscribed(0)
    for seq in (300, 200):
        gaps.add(seq)
    assert gaps.lost == 498
    assert gaps.add(100) == 99  # a third publisher: the 300 stream is forgotten ...
    assert gaps.add(50) == 0  # ... so one new stream may be it, and starts uncounted
