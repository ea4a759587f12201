"""Discrete train model of Wen et al. (2017), eq. (1)-(10), for any sample period.

Continuous dynamics, eq. (1)-(4), state ``x = (position m, velocity m/s)``::

    dx/dt = v,
    (1 + lambda) M dv/dt = F_drive - f_r(v) - M g sin(theta(x)),                      (1)-(3)
    f_r(v) = a0 + a1 v + a2 v^2 + w                                                   (7)

i.e. ``dx/dt = A x + B F_drive + E (f_r + F_grad)`` with ``A = [[0, 1], [0, 0]]``,
``B = [0, 1/M_eff]^T``, ``E = -B`` (4). Exact ZOH discretisation over a period ``T`` (6):
``A1 = e^{A T}``, ``B~ = int_0^T e^{A s} ds B``, ``E~ = int_0^T e^{A s} ds E``.

Resistance split, eq. (8)-(9): with ``v in [0, v_max]`` write ``v = v_max/2 + dv``, ``|dv| <=
v_max/2``, so ``a2 v^2 = a2 (v_max/2) v + a2 dv v`` and

    f_r = A2 x + F~ DeltaA(k) x + w + f~,   A2 = [0, a1 + a2 v_max/2],   f~ = a0,
    F~ = a2 v_max / 2,   DeltaA(k) = [0, dv(k) / (v_max/2)],   DeltaA DeltaA^T <= 1,

which gives eq. (10): ``x(k+1) = (A~ + E~ F~ DeltaA(k)) x(k) + B~ u(k) + E~ (f~ + F_grad(k))
+ E~ w(k)`` with ``A~ = A1 + E~ A2``. ``H = E~ F~`` is the column through which the
norm-bounded uncertainty enters; ``Eu`` is the matrix it multiplies (Lemma 1's ``E``).

Paper slips, and what this module does instead (the physically right thing):

* Eq. (7)/(9) multiply ``a0 + a1 v`` and ``a2 v^2`` by the mass ``M`` while Table I gives
  ``a0 = 3481.8, a1 = 144.92, a2 = 8.5212`` "without units". With ``M = 288 t`` that would be a
  resistance of ~1e9 N. The numbers are the Davis coefficients of the whole train in N,
  N/(m/s), N/(m/s)^2 (``train.yaml: davis: {a, b, c}``), so here ``f_r = a + b v + c v^2`` in N,
  ``A2 = [0, b + c v_max/2]``, ``f~ = a``, ``F~ = c v_max/2`` (no factor M).
* Table II's "gradient angle" values (-3, 3, -9) are per mille, not degrees or radians;
  ``Line.gradient_accel`` converts per mille to ``g sin(atan(permille/1000))``. The gravity
  force acts on the real mass ``M`` (eq. (2)), only the inertia uses ``(1 + lambda) M``.
* Section IV says "x(0) = 0.16", which is lambda copied; the initial position is 1333.8031 m.
* Table I is titled "high speed train" but describes a subway train (v_max = 22.23 m/s).
* Lemma 1 is applied in the paper with ``E = I`` (``uncertainty="paper"``): the bound then
  contains ``lambda_max(x^ x^^T) = |x^|^2``, which includes position^2 -- the bound depends on
  where the track's origin is, although the v^2 uncertainty only involves velocity. The exact
  structure is ``DeltaA = delta [0, 1]`` with a scalar ``|delta| <= 1``: ``Eu = [[0, 1]]``
  (``uncertainty="velocity"``), a valid and much tighter bound (only ``v^2`` enters).
* ``w`` (wind force, eq. (7)) is bounded by ``w^2 <= q``; the paper's ``q = 0.49`` is then N^2,
  a force of 0.7 N on a 288 t train, i.e. negligible. We keep ``q`` in N^2 as written.

Control input: the ATO's target acceleration ``a_Tar`` (m/s^2). The drive force is
``F_drive = control_mass * a`` where ``a`` is the achieved (delayed, lagged) control
acceleration; ``control_mass`` is the effective mass by default (the simulator's convention:
``a_Tar`` is the acceleration the drive aims to add). See :class:`Actuator`.

Pure: numpy/scipy only.
"""

from __future__ import annotations

import bisect
import math
from dataclasses import dataclass, field
from functools import cached_property, lru_cache

import numpy as np
from train_core.dynamics import GradientLookup
from train_core.model import Line, TrainParams

from ..numerics.discretize import zoh

__all__ = ["WenModel", "DiscreteWen", "Actuator", "discrete_matrices"]


@dataclass(frozen=True)
class DiscreteWen:
    """Matrices of eq. (6)-(10) for one sample period ``dt`` (s)."""

    dt: float  # s
    A1: np.ndarray  # (2, 2) e^{A dt}
    B: np.ndarray  # (2,) int e^{As} ds B: response to a drive force held over dt, per N
    E: np.ndarray  # (2,) int e^{As} ds E: response to a resistive force held over dt, per N
    A2: np.ndarray  # (2,) nominal linear resistance row, N per unit state
    A: np.ndarray  # (2, 2) A~ = A1 + E~ A2, eq. (10)
    F: float  # N/(m/s), F~ = c v_max / 2
    H: np.ndarray  # (2, 1) E~ F~, column of the norm-bounded uncertainty
    Eu: np.ndarray  # (r, 2) Lemma 1's E: I (paper) or [[0, 1]] (velocity only)

    def __post_init__(self):
        # the products eq. (21) uses at every step, once per period (the matrices are cached
        # per period: discrete_matrices): H H^T, its trace as sum(H * H), E E^T, and I (r x r)
        for name, value in (("HH", self.H @ self.H.T), ("hh", float(np.sum(self.H * self.H))),
                            ("EE", np.outer(self.E, self.E)),
                            ("I_u", np.eye(self.Eu.shape[0]))):
            if isinstance(value, np.ndarray):
                value.setflags(write=False)
            object.__setattr__(self, name, value)


@lru_cache(maxsize=64)
def discrete_matrices(meff: float, b: float, c: float, v_max: float, dt: float,
                      uncertainty: str = "paper") -> DiscreteWen:
    """Eq. (6), (9), (10) for effective mass ``meff`` (kg), Davis ``b, c`` and period ``dt``.

    Cached: the node calls this at every step with the same few periods.
    """
    Ac = np.array([[0.0, 1.0], [0.0, 0.0]])
    Bc = np.array([0.0, 1.0 / meff])
    A1, Bd = zoh(Ac, Bc, dt)
    Ed = -Bd  # E = -B in eq. (4): resistance and gravity oppose the drive
    A2 = np.array([0.0, b + c * v_max / 2.0])  # eq. (9), Davis in N (no factor M, see above)
    A = A1 + np.outer(Ed, A2)  # eq. (10)
    F = c * v_max / 2.0
    H = (Ed * F).reshape(2, 1)
    if uncertainty == "paper":
        Eu = np.eye(2)
    elif uncertainty == "velocity":
        Eu = np.array([[0.0, 1.0]])
    else:
        raise ValueError(f"uncertainty must be 'paper' or 'velocity', got {uncertainty!r}")
    for arr in (A1, Bd, Ed, A2, A, H, Eu):
        arr.setflags(write=False)
    return DiscreteWen(dt=dt, A1=A1, B=Bd, E=Ed, A2=A2, A=A, F=F, H=H, Eu=Eu)


@dataclass(frozen=True)
class WenModel:
    """The train/line model the filters share (believed or, for the oracle, true)."""

    mass: float  # kg, M (gravity acts on it, eq. (2))
    meff: float  # kg, (1 + lambda) M (inertia, eq. (3))
    a: float  # N, Davis a0
    b: float  # N/(m/s), Davis a1
    c: float  # N/(m/s)^2, Davis a2
    v_max: float  # m/s, speed bound of eq. (8)
    line: Line = field(repr=False)  # gradient profile (piecewise constant, Remark 1)
    q: float = 0.49  # N^2, bound on the squared wind force w^2 <= q (eq. (7))
    control_mass: float = 0.0  # kg, F_drive = control_mass * a_control; 0 means meff
    uncertainty: str = "paper"  # "paper" (Eu = I) or "velocity" (Eu = [0 1])

    @classmethod
    def from_params(cls, train: TrainParams, line: Line, q: float = 0.49,
                    v_max: float | None = None, uncertainty: str = "paper") -> WenModel:
        return cls(mass=train.mass, meff=train.effective_mass, a=train.davis.a,
                   b=train.davis.b, c=train.davis.c,
                   v_max=float(line.max_speed if v_max is None else v_max), line=line,
                   q=float(q), uncertainty=uncertainty)

    @property
    def drive_mass(self) -> float:
        return self.control_mass if self.control_mass > 0 else self.meff

    def discrete(self, dt: float) -> DiscreteWen:
        return discrete_matrices(self.meff, self.b, self.c, self.v_max, float(dt),
                                 self.uncertainty)

    @cached_property
    def _gradient(self) -> GradientLookup:
        """g sin(theta(x)) by bisection (hot path): the simulator's lookup with lambda = 0."""
        return GradientLookup(self.line, 0.0)

    def gradient_force(self, position: float) -> float:
        """N, F_grad = M g sin(theta(x)) (eq. (2)); positive uphill (opposes motion)."""
        return self.mass * self._gradient(position)

    def known_input(self, dm: DiscreteWen, position: float, control_accel: float) -> np.ndarray:
        """The known part of eq. (10): ``B~ F_drive + E~ (f~ + F_grad)`` (2-vector, SI)."""
        return dm.B * (self.drive_mass * control_accel) + dm.E * (
            self.a + self.gradient_force(position))

    def predict_mean(self, dm: DiscreteWen, x: np.ndarray, control_accel: float) -> np.ndarray:
        """Nominal prediction ``A~ x + B~ u + E~ (f~ + F_grad(x))`` of eq. (13)."""
        return dm.A @ x + self.known_input(dm, x[0], control_accel)

    @staticmethod
    def standstill(x: np.ndarray, x_pred: np.ndarray, dt: float) -> np.ndarray:
        """Stop instead of reversing: resistance and brakes cannot move a train backwards.

        If the linear prediction ends with ``v < 0``, the train stopped inside the step: with
        the step's mean deceleration ``a = (v_pred - v0) / dt`` it stops after ``v0 / |a|`` having
        covered ``v0^2 / (2 |a|)``, and stays there. (Departure needs a forward net force, which
        the linear model gives by itself.) Not in the paper: eq. (1) without this makes a
        stopped, braked train roll backwards at ~0.3 m/s^2 in the model.
        """
        if x_pred[1] >= 0.0:
            return x_pred
        v0 = max(float(x[1]), 0.0)
        a = (float(x_pred[1]) - float(x[1])) / dt if dt > 0 else -math.inf
        travel = 0.5 * v0 * v0 / -a if a < 0 else 0.0
        return np.array([float(x[0]) + travel, 0.0])

    def step_exact(self, dm: DiscreteWen, x: np.ndarray, control_accel: float,
                   wind: float = 0.0) -> np.ndarray:
        """Eq. (6) with the full ``a + b v + c v^2 + w`` held over the step (what eq. (10)
        describes exactly when ``|v - v_max/2| <= v_max/2``). For synthetic data in tests."""
        v = x[1]
        fr = self.a + self.b * v + self.c * v * v + wind
        return dm.A1 @ x + dm.B * (self.drive_mass * control_accel) + dm.E * (
            fr + self.gradient_force(x[0]))

    def ekf_step(self, dm: DiscreteWen, x: np.ndarray, control_accel: float
                 ) -> tuple[np.ndarray, np.ndarray]:
        """Exact-resistance prediction and its Jacobian (for the oracle EKF):
        ``x+ = A1 x + B~ F + E~ (a + b v + c v^2 + F_grad)``, ``J = A1 + E~ [0, b + 2 c v]``."""
        J = dm.A1 + np.outer(dm.E, [0.0, self.b + 2.0 * self.c * x[1]])
        return self.step_exact(dm, x, control_accel), J


class Actuator:
    """Believed actuator: target acceleration -> achieved control acceleration.

    Zheng et al. (2015) eq. (1)-(3) as ``train.yaml: brake`` states it: the command ``a_Tar``
    acts after a transport delay ``T`` and a first-order lag ``tau``; braking (``a_Tar < 0``)
    is scaled by the braking rate ``f``::

        tau da/dt = g(a_Tar(t - T)) - a,   g(c) = c if c >= 0 else f c.

    Not in Wen's model (which feeds ``u(kT)`` straight in), but ``a_Tar`` is what the filter
    receives, and feeding it undelayed would put a systematic input error of up to ~1 m/s^2 into
    every brake application. The map is deterministic and linear, so it is a known-input
    pre-filter, not a state: the filters' error equations (18) are unchanged.

    ``mean(t0, t1)`` integrates the lag exactly over the piecewise-constant delayed command and
    returns the mean achieved acceleration over ``[t0, t1]`` (the ZOH input of the step).

    Why not ``train_core.actuator.Actuator`` (the same eq. (1), event based): the filter needs
    the *mean* over each prediction step (the ZOH input of eq. (6)), not point values; it must
    accept late commands (effective from the latest known time: message order is not the
    world's) and run copies for predictions on copies; and ``enabled=False`` is Wen's plain
    ``u(kT)``. Its lag state at step ends is the event actuator's output
    (``test_wen_model.py`` checks both on a common grid).
    """

    def __init__(self, time_constant: float, delay: float, braking_rate: float = 1.0,
                 enabled: bool = True):
        self.tau = float(time_constant)
        self.delay = float(delay) if enabled else 0.0
        self.braking_rate = float(braking_rate)
        self.enabled = enabled
        self._cmds: list[tuple[float, float]] = []  # (stamp, a_Tar), stamps non-decreasing
        # when each command takes effect (stamp + delay), non-decreasing as the stamps are: the
        # lookups bisect it. A scan per lookup cost the robust filter more than real time at
        # 50 Hz, where a few seconds of commands wait ahead of the filter's time.
        self._acts: list[float] = []
        self._a = 0.0  # achieved acceleration at self._t
        self._t = -math.inf

    def copy(self) -> Actuator:
        new = Actuator.__new__(type(self))  # a subclass stays itself (the tests' oracle)
        new.__dict__.update(self.__dict__)
        new._cmds = list(self._cmds)
        new._acts = list(self._acts)
        return new

    def with_commands_of(self, other: Actuator) -> Actuator:
        """A copy of this lag state driven by ``other``'s commands (the filter's, known now)."""
        new = self.copy()
        new._cmds, new._acts = list(other._cmds), list(other._acts)
        return new

    def commands(self) -> int:
        """How many commands are held (an index for :meth:`acts_before`)."""
        return len(self._cmds)

    def acts_before(self, first: int, t: float) -> bool:
        """Whether a command from index ``first`` on takes effect before ``t``."""
        return first < len(self._acts) and self._acts[first] < t  # the earliest of them

    def command(self, stamp: float, a_tar: float) -> None:
        if self._cmds and stamp < self._cmds[-1][0]:
            stamp = self._cmds[-1][0]  # late command: effective from the latest known time
        self._cmds.append((float(stamp), float(a_tar)))
        self._acts.append(float(stamp) + self.delay)

    def _g(self, c: float) -> float:
        return c if c >= 0.0 else self.braking_rate * c

    def _delayed(self, s: float) -> float:
        """g(a_Tar(s - T)): the command in force at time s (0 before the first command)."""
        i = bisect.bisect_right(self._acts, s)  # the commands in effect by s
        return self._g(self._cmds[i - 1][1] if i else 0.0)

    def mean(self, t0: float, t1: float) -> float:
        """Mean achieved acceleration over [t0, t1]; advances the internal lag state to t1."""
        if not self.enabled:  # plain ZOH of the command in force at t0 (Wen's u(kT))
            c = self._delayed(t0)
            self._t = t1
            self._prune(t0)
            return c
        if not math.isfinite(self._t):
            self._t, self._a = t0, self._delayed(t0)
        t0 = self._t
        if t1 <= t0:
            return self._a
        # the commands taking effect inside (t0, t1) split the step into segments, each under
        # the command in force at its start: from acts[i] on, the last of the commands taking
        # effect then (several share a time: repeated stamps, late ones clamped); walked in
        # order instead of looked up per segment (a 50 Hz step of a second holds ~50 of them)
        acts, cmds, tau, f = self._acts, self._cmds, self.tau, self.braking_rate
        i, hi = bisect.bisect_right(acts, t0), bisect.bisect_left(acts, t1)
        integral, a = 0.0, self._a
        s0, c = t0, self._delayed(t0)
        while True:
            s1 = acts[i] if i < hi else t1
            d = s1 - s0
            if tau > 0:
                if d == 0.0:  # exp(0) = 1: the general step below, bit for bit, adds nothing
                    a = c + (a - c)  # to the integral; what it does to a it does here
                else:
                    decay = math.exp(-d / tau)
                    integral += c * d + (a - c) * tau * (1.0 - decay)  # int of the lag response
                    a = c + (a - c) * decay
            else:
                integral += c * d
                a = c
            if i >= hi:
                break
            if i == 0 or acts[i - 1] != s1:  # a new effect time: its last command rules
                j = i
                while j + 1 < hi and acts[j + 1] == s1:
                    j += 1
                v = cmds[j][1]
                c = v if v >= 0.0 else f * v  # g (eq. 1's braking rate)
            s0 = s1
            i += 1
        self._a, self._t = a, t1
        self._prune(t1)
        return integral / (t1 - t0)

    def _prune(self, t: float) -> None:
        """Drop commands that can no longer matter after ``t`` (keep the last one in force)."""
        keep_from = bisect.bisect_right(self._acts, t) - 1  # the last one in effect by t
        if keep_from > 0:
            del self._cmds[:keep_from]
            del self._acts[:keep_from]
