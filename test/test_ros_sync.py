"""Tests of the pure-Python stereo synchroniser."""

from hypothesis import given, settings
from hypothesis import strategies as st
import pytest

from stereo_vo_ros.ros.sync import StereoSynchronizer

MS = 1_000_000  # ns


def _feed(sync, events):
    """Feed (side, stamp_ns) events; items are (side, stamp) so pairs can be checked."""
    pairs = []
    for side, stamp in events:
        pairs += sync.add(side, stamp, (side, stamp))
    return pairs


def test_exact_pairs_equal_stamps_in_any_arrival_order():
    sync = StereoSynchronizer('exact')
    events = [('left', 100 * MS), ('right', 100 * MS), ('right', 200 * MS),
              ('left', 200 * MS), ('left', 300 * MS), ('right', 300 * MS)]
    pairs = _feed(sync, events)
    assert [p.stamp_ns for p in pairs] == [100 * MS, 200 * MS, 300 * MS]
    for p in pairs:
        assert p.left == ('left', p.stamp_ns) and p.right == ('right', p.stamp_ns)
    assert sync.stats.pairs == 3 and sync.stats.unsynchronized == 0


def test_exact_never_pairs_different_stamps():
    sync = StereoSynchronizer('exact', slop_s=1.0)  # slop ignored when exact
    pairs = _feed(sync, [('left', 100 * MS), ('right', 100 * MS + 1)])
    assert pairs == []
    # The right stream has moved past the left stamp: the left message can never pair.
    assert sync.stats.unmatched['left'] == 1 and sync.queued('right') == 1


def test_approximate_respects_the_slop_bound_to_the_nanosecond():
    slop_ns = 5 * MS
    sync = StereoSynchronizer('approximate', slop_s=slop_ns * 1e-9)
    assert len(_feed(sync, [('left', 1000 * MS), ('right', 1000 * MS + slop_ns)])) == 1
    sync = StereoSynchronizer('approximate', slop_s=slop_ns * 1e-9)
    assert _feed(sync, [('left', 1000 * MS), ('right', 1000 * MS + slop_ns + 1)]) == []


def test_approximate_picks_the_nearest_queued_partner():
    sync = StereoSynchronizer('approximate', slop_s=0.010)
    _feed(sync, [('right', 96 * MS), ('right', 99 * MS), ('right', 108 * MS)])
    (pair,) = _feed(sync, [('left', 100 * MS)])
    assert pair.right_stamp_ns == 99 * MS and pair.stamp_ns == 100 * MS
    # The older right message can never be paired now: counted as unmatched; the newer waits.
    assert sync.stats.unmatched['right'] == 1
    assert sync.queued('right') == 1


def test_pairs_carry_the_time_between_their_arrivals():
    now = [10.0]
    sync = StereoSynchronizer('exact', clock=lambda: now[0])
    assert sync.add_right(5, 'r') == []
    now[0] = 10.012
    (pair,) = sync.add_left(5, 'l')
    assert (pair.left, pair.right) == ('l', 'r')
    assert pair.arrival_gap_s == pytest.approx(0.012)


def test_late_and_duplicate_stamps():
    sync = StereoSynchronizer('exact')
    _feed(sync, [('left', 100 * MS), ('right', 100 * MS)])
    # Not newer than the last pair: late.
    assert _feed(sync, [('left', 100 * MS), ('right', 50 * MS)]) == []
    assert sync.stats.late == {'left': 1, 'right': 1}
    # Same stamp twice on one side before its partner: the newer item replaces the older.
    sync.add('left', 200 * MS, 'first')
    sync.add('left', 200 * MS, 'second')
    (pair,) = sync.add('right', 200 * MS, 'r')
    assert pair.left == 'second'
    assert sync.stats.duplicates['left'] == 1


def test_out_of_order_arrival_within_the_queue_still_pairs():
    sync = StereoSynchronizer('exact')
    pairs = _feed(sync, [('left', 300 * MS), ('left', 200 * MS), ('right', 200 * MS),
                         ('right', 300 * MS)])
    assert [p.stamp_ns for p in pairs] == [200 * MS, 300 * MS]


def test_unmatched_messages_are_counted_when_the_other_side_moves_on():
    sync = StereoSynchronizer('approximate', slop_s=0.002)
    # Right camera drops every second frame.
    events = []
    for k in range(10):
        events.append(('left', k * 100 * MS))
        if k % 2 == 0:
            events.append(('right', k * 100 * MS + MS))
    pairs = _feed(sync, events)
    assert len(pairs) == 5
    assert sync.stats.unmatched['left'] + sync.queued('left') == 5
    assert sync.stats.unmatched['right'] == 0


def test_memory_is_bounded_when_one_side_is_silent():
    sync = StereoSynchronizer('exact', queue_size=7)
    for k in range(10_000):
        assert sync.add('left', k * MS, k) == []
    assert sync.queued('left') == 7
    assert sync.stats.unmatched['left'] == 10_000 - 7
    sync.reset()
    assert sync.queued('left') == 0 and sync.stats.unsynchronized == 0


def test_stamps_jumping_back_restart_the_pairing():
    """A looping bag: pairing starts afresh instead of dropping everything as late."""
    sync = StereoSynchronizer('exact')
    loop = [(side, k * 100 * MS) for k in range(1, 16) for side in ('left', 'right')]
    first = _feed(sync, loop)
    second = _feed(sync, loop[:10])
    assert [p.stamp_ns for p in first] == [k * 100 * MS for k in range(1, 16)]
    assert [p.stamp_ns for p in second] == [k * 100 * MS for k in range(1, 6)]
    assert sync.stats.restarts == 1 and sync.stats.unsynchronized == 0
    assert sync.newest('left') == sync.newest('right') == 500 * MS
    # A jump back shorter than the threshold is an out-of-order stamp: dropped as late.
    assert sync.add('left', 50 * MS, 'x') == [] and sync.stats.late['left'] == 1
    assert sync.stats.restarts == 1


def test_restart_drops_what_was_queued_and_counts_it():
    sync = StereoSynchronizer('approximate', slop_s=0.001, restart_jump_s=0.5)
    _feed(sync, [('left', 1000 * MS), ('left', 1100 * MS), ('right', 1100 * MS),
                 ('left', 1200 * MS)])
    assert sync.queued('left') == 1
    # The right camera restarts first: the queued left message can never pair.
    assert _feed(sync, [('right', 100 * MS)]) == []
    assert sync.stats.restarts == 1 and sync.queued('left') == 0
    assert sync.stats.unmatched['left'] == 2  # 1000 ms (earlier) and 1200 ms (restart)
    (pair,) = _feed(sync, [('left', 100 * MS)])
    assert pair.stamp_ns == pair.right_stamp_ns == 100 * MS


def test_invalid_arguments():
    with pytest.raises(ValueError, match='nearest'):
        StereoSynchronizer('nearest')
    with pytest.raises(ValueError, match='-0.1'):
        StereoSynchronizer('approximate', slop_s=-0.1)
    with pytest.raises(ValueError, match='middle'):
        StereoSynchronizer().add('middle', 0, None)
    with pytest.raises(ValueError, match='restart jump'):
        StereoSynchronizer(restart_jump_s=0.0)


@settings(max_examples=200, deadline=None)
@given(
    slop_ms=st.integers(0, 8),
    queue_size=st.integers(1, 6),
    steps=st.lists(st.tuples(st.sampled_from(['left', 'right']), st.integers(-3, 40)),
                   max_size=80),
)
def test_invariants_on_random_streams(slop_ms, queue_size, steps):
    """Pairs respect the slop and increase; every message is accounted for exactly once."""
    sync = StereoSynchronizer('approximate', slop_s=slop_ms * 1e-3, queue_size=queue_size)
    clock = {'left': 0, 'right': 0}
    total = 0
    pairs = []
    for side, jump in steps:
        clock[side] = max(0, clock[side] + jump * MS)  # mostly increasing, sometimes not
        pairs += sync.add(side, clock[side], (side, clock[side]))
        total += 1
        assert sync.queued(side) <= queue_size
    for p in pairs:
        assert abs(p.stamp_ns - p.right_stamp_ns) <= slop_ms * MS
        assert p.left == ('left', p.stamp_ns) and p.right == ('right', p.right_stamp_ns)
    for a, b in zip(pairs, pairs[1:]):
        assert b.stamp_ns > a.stamp_ns and b.right_stamp_ns > a.right_stamp_ns
    s = sync.stats
    assert s.restarts == 0
    accounted = 2 * s.pairs + s.unsynchronized + sum(s.duplicates.values()) + \
        sync.queued('left') + sync.queued('right')
    assert accounted == total


@settings(max_examples=200, deadline=None)
@given(
    slop_ms=st.integers(0, 8),
    steps=st.lists(st.tuples(st.sampled_from(['left', 'right']),
                             st.sampled_from([100, 100, 100, 0, 3, -3, -1500, -5000, 2000])),
                   max_size=80),
)
def test_invariants_with_restarts(slop_ms, steps):
    """With stamps jumping back (restarts) every message is still accounted for once."""
    sync = StereoSynchronizer('approximate', slop_s=slop_ms * 1e-3, queue_size=4)
    clock = {'left': 10_000 * MS, 'right': 10_000 * MS}
    total = 0
    for side, jump in steps:
        clock[side] = max(0, clock[side] + jump * MS)
        for p in sync.add(side, clock[side], (side, clock[side])):
            assert abs(p.stamp_ns - p.right_stamp_ns) <= slop_ms * MS
        total += 1
        assert sync.queued(side) <= 4
    s = sync.stats
    accounted = 2 * s.pairs + s.unsynchronized + sum(s.duplicates.values()) + \
        sync.queued('left') + sync.queued('right')
    assert accounted == total
