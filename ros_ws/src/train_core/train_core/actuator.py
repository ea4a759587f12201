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

Pure module: the standard library only.
"""

from __future__ import annotations

import math
from collections import deque

_EPS = 1e-9  # s, tolerance when comparing event times


def effective_input(u: float, f: float) -> float:
    """u_eff of eq. (1): braking commands (u < 0) are scaled by the braking rate f."""
    return u if u >= 0.0 else f * u


class Actuator:
    """Exact delay ``T`` followed by a first-order lag ``tau`` (Zheng eq. (1)), scalar state.

    ``a0`` is the output at ``t0``; ``u0`` the command that was issued before ``t0`` and fills the
    delay line (Zheng Sec. 4 starts mid-braking with a_hat(0) = -1 m/s^2 and the pipe full of -1;
    a train at rest starts with a0 = u0 = 0).
    """

    def __init__(self, time_constant: float, delay: float, a0: float = 0.0, u0: float = 0.0,
                 t0: float = 0.0):
        if not time_constant > 0.0:
            raise ValueError("time_constant must be > 0")
        if not delay >= 0.0:
            raise ValueError("delay must be >= 0")
        self.tau = float(time_constant)
        self.delay = float(delay)
        self.t = float(t0)
        self.a = float(a0)  # m/s^2, output a_hat(t)
        self.u = float(u0)  # m/s^2, delayed command a_Tar(t - T) in force at self.t
        self.last_command = float(u0)  # most recent command issued (not yet necessarily active)
        self._pipe: deque[tuple[float, float]] = deque()  # (activation time, command)

    def copy(self) -> Actuator:
        new = Actuator.__new__(Actuator)
        new.tau, new.delay, new.t, new.a, new.u = self.tau, self.delay, self.t, self.a, self.u
        new.last_command = self.last_command
        new._pipe = deque(self._pipe)
        return new

    def command(self, t: float, a_tar: float) -> None:
        """Issue a_Tar at time ``t`` (>= self.t); it becomes the input at ``t + T``."""
        self.last_command = float(a_tar)
        t_act = t + self.delay
        if self._pipe and t_act < self._pipe[-1][0] - _EPS:
            raise ValueError("commands must be issued in time order")
        self._pipe.append((t_act, float(a_tar)))
        self._activate()

    def _activate(self) -> None:
        pipe = self._pipe
        while pipe and pipe[0][0] <= self.t + _EPS:
            self.u = pipe.popleft()[1]

    def next_switch(self) -> float:
        """Next time (> self.t) at which the delayed input changes; inf if none is pending."""
        return self._pipe[0][0] if self._pipe else math.inf

    def segment(self, h: float, f: float) -> tuple[float, float, float]:
        """Advance by ``h`` with constant input (caller ensures no switch inside (t, t + h)).

        Returns (a_hat(t), a_hat(t + h/2), a_hat(t + h)) -- the values RK4 needs.
        """
        ue = self.u if self.u >= 0.0 else f * self.u
        a0 = self.a
        e = math.exp(-0.5 * h / self.tau)
        a_mid = ue + (a0 - ue) * e
        a_end = ue + (a_mid - ue) * e
        self.a = a_end
        self.t += h
        self._activate()
        return a0, a_mid, a_end

    def advance(self, t_new: float, f: float = 1.0) -> float:
        """Exact evolution to ``t_new`` (splitting at activation times); returns a_hat(t_new)."""
        while self.t < t_new - _EPS:
            t_stop = min(t_new, self.next_switch())
            self.segment(t_stop - self.t, f)
            self.t = t_stop  # avoid round-off accumulation
            self._activate()
        return self.a


def step_response(t, amplitude: float, time_constant: float, delay: float, f: float = 1.0):
    """Closed form of eq. (1) for a step a_Tar = amplitude at t = 0 from rest (test oracle).

    a_hat(t) = 0 for t < T and u_eff (1 - exp(-(t - T) / tau)) afterwards.
    """
    import numpy as np

    t = np.asarray(t, dtype=float)
    ue = effective_input(amplitude, f)
    return np.where(t < delay, 0.0, ue * (1.0 - np.exp(-(t - delay) / time_constant)))
