"""``core/online/arrival.py``: how far the world's clock can be past a simulated-time node's."""

import pytest

from train_estimation.core.online.arrival import SimArrival


def test_before_the_clock_moves_nothing_is_known_of_its_pace():
    a = SimArrival()
    assert a.observe(30.0, 100.0) == (30.0, 0.0)
    assert a.observe(30.0, 100.5) == (30.0, 0.0)


def test_a_clock_that_reaches_the_node_at_every_tick_is_one_tick_fine():
    """10x: the world's clock ticks 0.1 s every 10 ms of steady time, and each message is read
    just after its tick came: the resolution is the tick."""
    a = SimArrival()
    for k in range(100):
        recv, res = a.observe(30.0 + 0.1 * k, 100.0 + 0.01 * k + 1e-4)
        assert recv == 30.0 + 0.1 * k
    assert res == pytest.approx(0.1)


@pytest.mark.parametrize("lost", [1, 3, 10])
def test_a_clock_whose_ticks_were_lost_is_allowed_what_it_ran_since(lost):
    """The same world, and ``lost`` /clock messages that never reach the node while its data
    do: each message's true arrival (the world's time then) lies within ``resolution`` after
    ``recv``, to the pace's precision (a message read a tick after the last one the node
    saw was refused as 0.3 s ahead of its clock with the resolution one tick)."""
    a = SimArrival()
    for k in range(50):
        a.observe(30.0 + 0.1 * k, 100.0 + 0.01 * k)
    last_ros, last_wall = 30.0 + 0.1 * 49, 100.0 + 0.01 * 49
    for j in range(1, lost + 1):
        true = last_ros + 0.1 * j  # the world's clock when the message came
        recv, res = a.observe(last_ros, last_wall + 0.01 * j)
        assert recv == last_ros
        assert recv + res == pytest.approx(true)
    # the next tick that reaches the node: one step of (lost + 1) ticks seen, the largest
    recv, res = a.observe(last_ros + 0.1 * (lost + 1), last_wall + 0.01 * (lost + 1))
    assert res == pytest.approx(0.1 * (lost + 1))


def test_a_world_that_waits_runs_at_its_own_pace():
    """A world paced by its nodes (the simulator waits for the estimates) runs slower than its
    rate factor: the pace is the one measured, simulated over steady time."""
    a = SimArrival()
    for k in range(64):  # 0.1 s every 20 ms: a 5x world
        a.observe(10.0 + 0.1 * k, 50.0 + 0.02 * k)
    recv, res = a.observe(10.0 + 0.1 * 63, 50.0 + 0.02 * 63 + 0.1)
    assert res == pytest.approx(0.5)
