"""train_core.lag: the first-order recurrence is scipy's lfilter with the same arithmetic."""

import numpy as np
import pytest
from scipy.signal import lfilter
from train_core.lag import _first_order, first_order


@pytest.mark.parametrize("n", [1, 2, 3, 17, 6000])
@pytest.mark.parametrize("a", [0.0, 0.7788007830714049, 0.999])
def test_first_order_is_lfilter_bit_for_bit(n, a):
    x = np.random.default_rng(n).normal(size=n) * 3.0
    b = 1.0 - a if a else 0.1
    want = lfilter([0.0, b], [1.0, -a], x)
    assert np.array_equal(first_order(x, a, b), want)
    assert np.array_equal(_first_order(x, a, b), want)  # the interpreted loop too


def test_first_order_takes_any_float_array_view():
    x = np.arange(20.0)[::2]  # not contiguous
    assert np.array_equal(first_order(x, 0.5, 0.5), lfilter([0.0, 0.5], [1.0, -0.5], x))


@pytest.mark.parametrize("part", ["traction", "braking"])
def test_grid_part_holds_each_command_from_its_first_grid_point(part):
    """actuator.grid_part: the command on the grid is the last one stamped at or before
    t - delay (1e-9 s tolerance), 0 before the first; then the lag. Checked against that rule
    written out, with stamps on the grid's lattice, two at one instant, before the grid and
    after its end."""
    from train_core.actuator import grid_part

    rng = np.random.default_rng(3)
    t_grid = 5.0 + 0.02 * np.arange(2000)
    ctrl_t = np.sort(np.r_[0.5, 7.3, 7.3, np.round(rng.uniform(5.0, 45.0, 300), 1), 50.0])
    ctrl_a = rng.normal(size=ctrl_t.size)
    delay, tau = 1.2, 0.4
    cmd = np.zeros(t_grid.size)
    for k, t in enumerate(t_grid):
        n = int(np.sum(ctrl_t <= t - delay + 1e-9))
        cmd[k] = ctrl_a[n - 1] if n else 0.0
    cmd = np.maximum(cmd, 0.0) if part == "traction" else np.minimum(cmd, 0.0)
    e = np.exp(-(t_grid[1] - t_grid[0]) / tau)  # the grid's own step
    want = lfilter([0.0, 1.0 - e], [1.0, -e], cmd)
    assert np.array_equal(grid_part(t_grid, ctrl_t, ctrl_a, tau, delay, part), want)


@pytest.mark.parametrize("part", ["traction", "braking"])
def test_a_command_inside_a_grid_step_acts_from_its_stamp_with_substep(part):
    """actuator.grid_part with ``substep``: commands stamped anywhere (a producer off the
    grid's lattice, two in one step) give on a 0.1 s grid the lag's exact response, the one a
    1 ms grid with every stamp on it gives at the same instants; stamps on the lattice give
    the same bits as without it."""
    from train_core.actuator import grid_part

    rng = np.random.default_rng(4)
    ctrl_t = np.sort(np.round(rng.uniform(5.0, 45.0, 300), 3))
    ctrl_a = rng.normal(size=ctrl_t.size)
    delay, tau = 1.2, 0.4
    fine = 5.0 + 0.001 * np.arange(50001)
    exact = grid_part(fine, ctrl_t, ctrl_a, tau, delay, part)
    coarse = fine[::100]
    got = grid_part(coarse, ctrl_t, ctrl_a, tau, delay, part, substep=True)
    assert np.max(np.abs(got - exact[::100])) < 1e-9
    held = grid_part(coarse, ctrl_t, ctrl_a, tau, delay, part)
    assert np.max(np.abs(held - exact[::100])) > 0.05  # up to a step late without it
    on = np.round(ctrl_t, 1)
    assert np.array_equal(grid_part(coarse, on, ctrl_a, tau, delay, part, substep=True),
                          grid_part(coarse, on, ctrl_a, tau, delay, part))
