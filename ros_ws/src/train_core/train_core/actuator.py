"""Traction/brake actuator after Zheng et al. (2015) eq. (1): exact delay + first-order lag.

Zheng et al. eq. (1) (the paper prints ``a_Tar(t - tau)``; the text below it defines the transport
delay as ``T``, so the delayed command is ``a_Tar(t - T)``)::

    d a_hat / dt = -a_hat / tau + u_eff(t) / tau,
    u_eff(t) = a_Tar(t - T)            if a_Tar(t - T) >= 0   (traction: f does not apply)
             = f(t) * a_Tar(t - T)     if a_Tar(t - T) <  0   (braking: scaled by the braking rate)

``a_hat`` is the control acceleration (m/s^2) the actuator delivers. The braking rate ``f`` ("the
ratio of the actual braking power with the expected braking power", Zheng Sec. 2) multiplies the
braking part only; Zheng's experiment is pure braking, where both readings agree. ``f`` enters
*before* the lag, exactly as in eq. (1).

The world uses the exact delay: commands wait in a FIFO and become active at ``t_issue + T``;
between activations the input is constant and the lag has the closed form

    a_hat(t + h) = u + (a_hat(t) - u) exp(-h / tau).

Pade's ``(lambda - s) / (lambda + s)`` with ``lambda = 2 / T`` is the estimators' approximation,
never the world's. A time-varying ``f(t)`` is held at its mid-step value over each (<= 10 ms)
integration step; Zheng's drift of 0.005 per second changes f by 5e-5 per step.

Two implementations of the one model, because they compute different things:

* :class:`Actuator` (event based, exact): the output ``a_hat`` with ``f`` applied, at any time,
  with commands at any stamps -- what the world, the driver and ``motion`` step through.
* :func:`grid_output` (on a uniform grid, vectorised): the traction and the braking parts
  *separately and before f* over a whole recorded run, the regressors of ``identify`` and
  ``diagnose`` where ``f`` (and the traction gain) are unknown coefficients of a linear fit.
  The command is sampled at the grid points (held over each grid step), so it equals
  :class:`Actuator` exactly when command stamps plus delay fall on the grid (the usual 0.1 s
  lattice), and ``traction + f * braking`` is then the event-based output
  (``test_sim_physics.py`` checks this on a common grid).

Pure module: the standard library only (numpy/scipy imported inside the grid function).
"""

from __future__ import annotations

import math
from collections import deque

_EPS = 1e-9  # s, tolerance when comparing event times


def effective_input(u: float, braking_rate: float) -> float:
    """u_eff of eq. (1): braking commands (u < 0) are scaled by the braking rate f."""
    return u if u >= 0.0 else braking_rate * u


class Actuator:
    """Exact delay followed by a first-order lag ``tau`` (Zheng eq. (1)), scalar state.

    ``a0`` is the output at ``t0``; ``u0`` the command that was issued before ``t0`` and fills the
    delay line (Zheng Sec. 4 starts mid-braking with a_hat(0) = -1 m/s^2 and the pipe full of -1;
    a train at rest starts with a0 = u0 = 0).

    Traction and braking have their own transport delay (``delay`` and ``brake_delay``, default
    the same): the drive and the brake are separate chains on a real train (the brake's is
    pneumatic, often slower; docs/interfaces.md's ``brake_delay`` cause). A command is split at 0,
    its traction part max(a_Tar, 0) enters the traction pipe and its braking part min(a_Tar, 0)
    the brake pipe; the lag's input is the sum of the two delayed parts, the braking one scaled
    by f. With equal delays this is exactly eq. (1) (one of the two parts is always 0).
    """

    def __init__(self, time_constant: float, delay: float, a0: float = 0.0, u0: float = 0.0,
                 t0: float = 0.0, brake_delay: float | None = None):
        if not time_constant > 0.0:
            raise ValueError("time_constant must be > 0")
        if not delay >= 0.0:
            raise ValueError("delay must be >= 0")
        brake_delay = delay if brake_delay is None else float(brake_delay)
        if not brake_delay >= 0.0:
            raise ValueError("brake_delay must be >= 0")
        self.tau = float(time_constant)
        self.delay = float(delay)
        self.brake_delay = brake_delay
        self.t = float(t0)
        self.a = float(a0)  # m/s^2, output a_hat(t)
        # m/s^2, the braking part of a_hat (the lag of f * braking part; the lag is linear, so
        # a_hat = lag(traction part) + lag(f * braking part) exactly): what a power limit and an
        # adhesion section act on separately (dynamics.py). At t0 the output's sign says which.
        self.a_br = min(float(a0), 0.0)
        self.br_stages = (self.a_br, self.a_br, self.a_br)  # a_br at t, t + h/2, t + h of the
        # last segment (m/s^2)
        self.track_br = False  # keep a_br up to date (only the drive effects need it)
        self.u_tr = max(float(u0), 0.0)  # m/s^2, delayed traction part in force at self.t
        self.u_br = min(float(u0), 0.0)  # m/s^2, delayed braking part in force at self.t
        self.last_command = float(u0)  # most recent command issued (not yet necessarily active)
        self._pipe: deque[tuple[float, float]] = deque()  # traction: (activation time, part)
        self._bpipe: deque[tuple[float, float]] = deque()  # braking: (activation time, part)

    @property
    def u(self) -> float:
        """m/s^2, the delayed command in force (traction part + braking part, before f)."""
        return self.u_tr + self.u_br

    def effective(self, braking_rate: float) -> float:
        """u_eff of eq. (1) now: traction part + f * braking part."""
        return self.u_tr + braking_rate * self.u_br

    def copy(self) -> Actuator:
        new = Actuator.__new__(Actuator)
        new.__dict__.update(self.__dict__)
        new._pipe = deque(self._pipe)
        new._bpipe = deque(self._bpipe)
        return new

    def command(self, t: float, a_tar: float) -> None:
        """Issue a_Tar at time ``t`` (>= self.t); its traction part becomes the input at
        ``t + delay``, its braking part at ``t + brake_delay``."""
        self.last_command = float(a_tar)
        for pipe, part, d in ((self._pipe, max(float(a_tar), 0.0), self.delay),
                              (self._bpipe, min(float(a_tar), 0.0), self.brake_delay)):
            t_act = t + d
            if pipe and t_act < pipe[-1][0] - _EPS:
                raise ValueError("commands must be issued in time order")
            pipe.append((t_act, part))
        self._activate()

    def _activate(self) -> None:
        t = self.t + _EPS
        pipe, bpipe = self._pipe, self._bpipe
        while pipe and pipe[0][0] <= t:
            self.u_tr = pipe.popleft()[1]
        while bpipe and bpipe[0][0] <= t:
            self.u_br = bpipe.popleft()[1]

    def next_switch(self) -> float:
        """Next time (> self.t) at which the delayed input changes; inf if none is pending."""
        a = self._pipe[0][0] if self._pipe else math.inf
        b = self._bpipe[0][0] if self._bpipe else math.inf
        return a if a < b else b

    def segment(self, h: float, braking_rate: float) -> tuple[float, float, float]:
        """Advance by ``h`` with constant input (caller ensures no switch inside (t, t + h)).

        Returns (a_hat(t), a_hat(t + h/2), a_hat(t + h)) -- the values RK4 needs; the braking
        part's three values are left in ``br_stages``.
        """
        ub = braking_rate * self.u_br
        ue = self.u_tr + ub
        a0 = self.a
        e = math.exp(-0.5 * h / self.tau)
        a_mid = ue + (a0 - ue) * e
        a_end = ue + (a_mid - ue) * e
        self.a = a_end
        if not self.track_br:
            self.t += h
            self._activate()
            return a0, a_mid, a_end
        b0 = self.a_br
        b_mid = ub + (b0 - ub) * e
        b_end = ub + (b_mid - ub) * e
        self.a_br = b_end
        self.br_stages = (b0, b_mid, b_end)
        self.t += h
        self._activate()
        return a0, a_mid, a_end

    def advance(self, t_new: float, braking_rate: float = 1.0) -> float:
        """Exact evolution to ``t_new`` (splitting at activation times); returns a_hat(t_new)."""
        while self.t < t_new - _EPS:
            t_stop = min(t_new, self.next_switch())
            self.segment(t_stop - self.t, braking_rate)
            self.t = t_stop  # avoid round-off accumulation
            self._activate()
        return self.a


def step_response(t, amplitude: float, time_constant: float, delay: float,
                  braking_rate: float = 1.0):
    """Closed form of eq. (1) for a step a_Tar = amplitude at t = 0 from rest (test oracle).

    a_hat(t) = 0 for t < T and u_eff (1 - exp(-(t - T) / tau)) afterwards.
    """
    import numpy as np

    t = np.asarray(t, dtype=float)
    ue = effective_input(amplitude, braking_rate)
    return np.where(t < delay, 0.0, ue * (1.0 - np.exp(-(t - delay) / time_constant)))


SUBSTEP_RES = 1e-6  # s: a command stamped closer than this before a grid point acts from it


def grid_output(t_grid, ctrl_t, ctrl_a, tau: float, delay: float,
                brake_delay: float | None = None, substep: bool = False):
    """(traction, braking) actuator outputs on ``t_grid`` (uniform): delayed zero-order-hold
    command split at zero, each through the first-order lag tau (exact discretisation); the
    braking part before the braking rate f (module docstring: why this and :class:`Actuator`).

    The traction part is delayed by ``delay``, the braking part by ``brake_delay`` (default the
    same: the brake chain of :class:`Actuator`). The command before the first stamp is 0
    (Zheng eq. (1): a_Tar(t - T) = 0 for t <= T). ``substep``: each command acts from its own
    stamp, not from the grid point after it (:func:`grid_part`).
    """
    return (grid_part(t_grid, ctrl_t, ctrl_a, tau, delay, "traction", substep),
            grid_part(t_grid, ctrl_t, ctrl_a, tau, delay if brake_delay is None
                      else brake_delay, "braking", substep))


def grid_part(t_grid, ctrl_t, ctrl_a, tau: float, delay: float, part: str,
              substep: bool = False):
    """One part of :func:`grid_output`: ``part`` "traction" (the command's positive part) or
    "braking" (its negative part), delayed by ``delay`` and lagged by ``tau`` on ``t_grid``
    (an analysis that re-times only one part computes only that one).

    Each command is held from the first grid point at or after its (delayed) stamp. With
    ``substep`` (stamps in order), a command that falls inside a grid step acts from its stamp
    on: the lag's exact response to an input that switches at ``s`` within the step
    (t_k-1, t_k] is that of the input held over it at ``u_old + (u_new - u_old) (1 -
    exp(-(t_k - s) / tau)) / (1 - exp(-dt / tau))``. Without it a producer whose commands are
    stamped off the grid's lattice has its actuator up to a grid step late (0.1 s: identify's
    mass and braking rate 6-10 standard errors off on another simulator's nominal runs). A
    stamp within 1 us of a grid point is on it: on-lattice data gives the same bits either way.
    """
    import numpy as np

    from .lag import first_order

    clip = {"traction": np.maximum, "braking": np.minimum}[part]
    t_grid = np.asarray(t_grid, float)
    dt = t_grid[1] - t_grid[0]
    e = np.exp(-dt / tau)
    # The grid, the delay and the command stamps often sit on one lattice (0.1 s): without
    # a tolerance, round-off puts some grid points one command late, a 0.1 s jitter of the
    # input that biased a, c and f on metro_demo (found by benchmarks/bench_identify.py).
    # i[k] = (number of stamps <= t_grid[k] - d + 1e-9) - 1, counted from the stamps' side
    # (each stamp's first grid point at or after it): a search per command instead of
    # per grid point, the same comparisons
    x = t_grid - delay + 1e-9
    first = np.searchsorted(x, ctrl_t, side="left")
    ordered = first.size and np.all(first[1:] >= first[:-1])
    if ordered:
        # stamps in order (as recorded): each command held from its first grid point to the
        # next one's, 0 before the first: the same selection as below, a fifth of its time
        a = np.asarray(ctrl_a, float)
        cmd = np.repeat(np.concatenate([[0.0], a]), np.diff(np.concatenate([[0], first,
                                                                            [x.size]])))
    else:
        i = np.cumsum(np.bincount(first, minlength=x.size + 1)[:x.size]) - 1
        cmd = np.where(i >= 0, ctrl_a[np.clip(i, 0, None)], 0.0)
    u = clip(cmd, 0.0)
    if substep and ordered:
        # each command's step of the clipped input, from its stamp to the end of its grid step
        jump = np.diff(np.concatenate([[0.0], clip(a, 0.0)]))
        inner = (first >= 1) & (first < x.size)
        k = first[inner]
        lead = t_grid[k] - (np.asarray(ctrl_t, float)[inner] + delay)  # s before t_k
        on = lead > SUBSTEP_RES
        np.add.at(u, k[on] - 1, jump[inner][on] * -np.expm1(-lead[on] / tau) / (1.0 - e))
    # y[k] = e y[k-1] + (1 - e) x[k-1]: exact for a command held over each grid step
    return first_order(u, e, 1.0 - e)

