"""ThreadChoice: all threads while they pay, one while the cores are taken, and back."""

import pytest

from signal_light_node.model.backends.thread_choice import ThreadChoice


def run(choice: ThreadChoice, steps: int, ms_per_track: dict, tracks: int = 32) -> list:
    """Step ``steps`` times with the given cost per thread count; the counts used."""
    used = []
    for _ in range(steps):
        threads = choice.next()
        used.append(threads)
        choice.record(threads, tracks, ms_per_track[threads] * tracks / 1e3)
    return used


def test_measures_both_counts_first_then_keeps_the_faster_with_probes():
    choice = ThreadChoice(2, min_speedup=1.2, probe_every=10)
    used = run(choice, 44, {1: 1.5, 2: 1.0})  # quiet: 2 threads 1.5x faster
    assert used[:4] == [2, 2, 1, 1]  # each count's first run is a warm-up
    assert used[4:].count(1) == 4  # one probe of 1 thread every 10 steps
    assert choice.preferred == 2


def test_a_slow_first_run_does_not_decide():
    choice = ThreadChoice(2, min_speedup=1.2, probe_every=10)
    first = {1: 1.5, 2: 20.0}  # onnxruntime's first run of a shape
    used = [choice.next()]
    choice.record(used[0], 32, first[used[0]] * 32 / 1e3)
    used += run(choice, 20, {1: 1.5, 2: 1.0})
    assert used[-15:].count(2) >= 14


def test_one_thread_when_a_second_does_not_pay_and_back_when_it_does():
    choice = ThreadChoice(2, min_speedup=1.2, probe_every=10, weight=0.3)
    run(choice, 30, {1: 1.3, 2: 0.9})
    assert choice.preferred == 2
    # Another process takes a core: two threads are now no faster than one.
    used = run(choice, 60, {1: 1.4, 2: 1.6})
    switched = used.index(1)
    assert switched <= 3  # the running mean of 2 threads rises at once
    assert used[switched:].count(2) <= 6  # then only probes
    assert choice.preferred == 1
    # The core is free again: the next probe of 2 threads brings it back.
    used = run(choice, 20, {1: 1.3, 2: 0.9})
    assert choice.preferred == 2 and used[-9:].count(2) >= 8  # and a probe of 1


def test_small_speedups_do_not_pay():
    choice = ThreadChoice(4, min_speedup=1.2)
    run(choice, 10, {1: 1.1, 4: 1.0})
    assert choice.preferred == 1


def test_records_of_other_counts_or_empty_steps_are_ignored():
    choice = ThreadChoice(2)
    choice.record(3, 32, 0.1)
    choice.record(2, 0, 0.1)
    assert choice.per_track == {2: None, 1: None}


@pytest.mark.parametrize("kwargs", [dict(most=1), dict(most=2, min_speedup=0.5),
                                    dict(most=2, probe_every=1), dict(most=2, weight=0)])
def test_bad_settings_are_refused(kwargs):
    with pytest.raises(ValueError):
        ThreadChoice(**kwargs)


def test_the_onnxruntime_backend_gives_the_same_outputs_on_either_count():
    import numpy as np

    pytest.importorskip("onnxruntime")
    from signal_light_node.model.backends.registry import create_backend

    backend = create_backend("onnxruntime", precision="fp32")
    if backend.threads < 2:
        pytest.skip("one CPU: nothing to choose")
    assert create_backend("onnxruntime", threads=2).thread_choice is None  # a given count
    crops = np.random.default_rng(0).integers(0, 256, (32, 64, 64, 3), dtype=np.uint8)
    state = backend.initial_state(32)
    outs = {}
    for _ in range(3):  # all threads twice (the first a warm-up), then one
        out = backend.step(crops, state)
        outs[backend.threads_in_use] = out
    assert set(outs) == {1, backend.threads}
    a, b = outs.values()
    assert all(np.array_equal(a.probs[t], b.probs[t]) for t in a.probs)
    assert np.array_equal(a.state, b.state)
