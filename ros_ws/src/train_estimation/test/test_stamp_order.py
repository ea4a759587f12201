"""The one judgement of duplicates, order and the horizon (core/numerics/stamp_order.py)."""

from train_estimation.core import reasons as R
from train_estimation.core.numerics.stamp_order import StampOrder


def test_order_is_by_stamp_against_the_estimate_and_the_horizon():
    o = StampOrder(horizon=10.0)
    assert o.judge("odometer", 5.0, 1, t=None) == ""  # no estimate yet: nothing to be behind
    assert o.judge("odometer", 4.999, 1, t=5.0) == R.OUT_OF_ORDER
    assert o.judge("odometer", 5.0, 1, t=5.0) == ""  # at the estimate's time: taken
    assert o.judge("odometer", 15.0, 1, t=5.0) == ""  # the horizon itself is inside
    assert o.judge("odometer", 15.001, 1, t=5.0) == R.FUTURE_STAMP
    assert o.judge(None, 4.0, t=5.0) == R.OUT_OF_ORDER  # a time (a prediction, a command)
    assert o.judge(None, 16.0, t=5.0) == R.FUTURE_STAMP


def test_seq_marks_duplicates_and_resets_never_order():
    o = StampOrder()
    assert not o.took("odometer", 1.0, 7)
    assert o.judge("odometer", 1.1, 7, t=1.0) == R.DUPLICATE  # the same seq again
    assert o.judge("odometer", 1.0, 8, t=1.0) == R.DUPLICATE  # the same stamp again
    assert o.judge("balise", 1.0, 7, t=1.0) == ""  # another kind: its own last reading
    # seq = 2**32 - 1 cannot blind the stream: a lower seq with a later stamp is a reset
    assert not o.took("odometer", 1.1, 2 ** 32 - 1)
    assert o.judge("odometer", 1.2, 0, t=1.1) == ""
    assert o.took("odometer", 1.2, 0)
    assert o.last["odometer"] == (0, 1.2)


def test_a_late_reading_leaves_the_last_one_in_place():
    o = StampOrder()
    o.took("odometer", 2.0, 5)
    assert not o.took("odometer", 1.5, 4)  # fused late (rewound): not a reset, not the last
    assert o.last["odometer"] == (5, 2.0)
    free = StampOrder(kind_order=False)
    free.took("odometer", 2.0, 5)
    free.took("odometer", 1.5, 4)
    assert free.last["odometer"] == (4, 1.5)


def test_commands_are_ordered_by_stamp_and_a_same_stamp_one_is_taken():
    o = StampOrder()
    o.took("control", 3.0)
    assert o.judge("control", 3.0) == ""
    assert o.judge("control", 2.9) == R.OUT_OF_ORDER
    assert not o.took("control", 3.5)


def test_a_copy_stamped_before_the_estimate_copies_first_or_not():
    both = dict(kind="odometer", stamp=1.0, seq=3, t=1.5)  # a copy of the last, and behind
    o = StampOrder(horizon=10.0)
    o.took("odometer", 1.0, 3)
    assert o.judge(**both) == R.OUT_OF_ORDER
    c = StampOrder(horizon=10.0, copies_first=True)
    c.took("odometer", 1.0, 3)
    assert c.judge(**both) == R.DUPLICATE
    # far ahead and a copy by seq
    assert o.judge("odometer", 1e9, 3, t=1.5) == R.FUTURE_STAMP
    assert c.judge("odometer", 1e9, 3, t=1.5) == R.DUPLICATE


def test_kind_order_refuses_a_reading_behind_its_kind_while_the_estimate_lags():
    # a balise that moved the calibration without moving the filter's time (t stays 1.0)
    o, free = StampOrder(), StampOrder(kind_order=False)
    for x in (o, free):
        x.took("balise", 2.0, 1)
    assert o.judge("balise", 1.5, 2, t=1.0) == R.OUT_OF_ORDER
    assert free.judge("balise", 1.5, 2, t=1.0) == ""


def test_copies_of_a_message_within_the_window():
    o = StampOrder(window=3)
    assert not o.copy_of("odometer", (1, 1.0))
    assert o.copy_of("odometer", (1, 1.0))
    assert not o.copy_of("balise", (1, 1.0))  # per kind
    for k in range(2, 5):
        o.copy_of("odometer", (k, float(k)))
    assert not o.copy_of("odometer", (1, 1.0))  # three messages later: out of the window


def test_a_sample_fused_at_another_stamp_with_its_count_is_a_copy():
    o = StampOrder(samples=2)
    o.fuse(7, 1.0, 33.8)
    assert o.elsewhere(7, 6.0, 33.8)  # re-stamped copy
    assert not o.elsewhere(7, 1.0, 33.8)  # the same stamp: judged by copy_of
    assert not o.elsewhere(7, 6.0, 40.0)  # another count: a new sample (a sender restarted)
    o.fuse(8, 1.1, 34.0)
    o.fuse(9, 1.2, 34.2)
    assert not o.elsewhere(7, 6.0, 33.8)  # only the last `samples` are kept


def test_copy_is_independent():
    o = StampOrder(horizon=5.0, copies_first=True, kind_order=False, window=4, samples=3)
    o.took("odometer", 1.0, 1)
    o.copy_of("odometer", (1, 1.0))
    o.fuse(1, 1.0, 2.0)
    c = o.copy()
    c.took("odometer", 2.0, 2)
    c.copy_of("odometer", (2, 2.0))
    c.fuse(2, 2.0, 3.0)
    assert o.last["odometer"] == (1, 1.0) and not o.copy_of("odometer", (2, 2.0))
    assert not o.elsewhere(2, 5.0, 3.0)
    assert (c.horizon, c.copies_first, c.kind_order, c.window, c.samples) == (5.0, True,
                                                                             False, 4, 3)
