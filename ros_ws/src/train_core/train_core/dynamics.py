"""Longitudinal train dynamics: mass point, Davis resistance, line gradient, standstill logic.

Newton's law along the track (Wen et al. 2017 eq. (1)-(3); model.py)::

    (1 + lambda) M dv/dt = F_drive - (a + b v + c v^2) - M g sin(theta(x)),      dx/dt = v

written per unit effective mass (the form Zheng et al. eq. (2) uses, v' = a_hat + d(t))::

    dv/dt = kappa * a_hat - (a + b v + c v^2) / ((1 + lambda) M) - g sin(theta(x)) / (1 + lambda)

``a_hat`` is the actuator output (actuator.py). The traction/brake controller turns a_hat into a
force for the train *it believes in*, F_drive = (1 + lambda_b) M_b a_hat, so on the true train
the drive acceleration is ``kappa * a_hat`` with kappa = (1 + lambda_b) M_b / ((1 + lambda) M).
Without a ``mass`` effect kappa = 1 and this is exactly Zheng's a_hat. This is what makes a wrong
mass visible in traction and braking, not only in the resistance term.

Two effects act on the delivered drive, not on the actuator (the controller still asks for
a_hat; the train delivers less):

* power limit ``p_spec`` (m^2/s^3, traction power per kg of believed effective mass, i.e.
  P = p_spec (1 + lambda_b) M_b in W): the traction part of a_hat is delivered up to p_spec / v,
  so a command a is met below the knee speed p_spec / a and the traction acceleration falls as
  p_spec / v above it (a constant-power converter); at v = 0 there is no cap.
* adhesion section ``(start, end, factor)``: while the train's reference point is on
  [start, end) the braking part of a_hat is delivered times ``factor`` (wet rail, leaves: the
  wheel-rail contact limits the force at once, so the change starts and ends at the section's
  ends, with no lag).

The actuator gives a_hat and its braking part a_br separately (actuator.py); the traction part is
a_hat - a_br. Both effects are evaluated at the RK4 stage states (x, v), as the gradient is.

Integration: classical RK4 on (x, v) with step h <= 10 ms; a_hat comes from the actuator's
closed form at the RK4 stage times (t, t + h/2, t + h), so the actuator is integrated exactly.

Standstill (the issue's "stops and stays stopped"):

* Resistance only opposes motion; the train never moves backwards. When v reaches 0 inside a
  step the stopping instant is located (secant on the RK4 solution), the train is put at rest
  there, and the rest of the step is spent at rest.
* A train at rest starts again only when the forward force exceeds the static resistance:
  kappa * a_hat - g sin(theta) / (1 + lambda) > a / ((1 + lambda) M).
* Roll-back: **never**. A stopped CBTC train is held by its brake (the ATO applies a holding
  brake whenever it is at rest), and we extend this to the rare case of a train that coasts to
  a stop on an up-grade without braking: it is held too. This keeps v >= 0 and the odometer's
  counted distance monotone.

Pure module: the standard library (bisect, math) in the hot loop; scalars only.
"""

from __future__ import annotations

import math
from bisect import bisect_right
from dataclasses import dataclass

from .model import G, Line, TrainParams


class GradientLookup:
    """Fast scalar lookup of g sin(theta(x)) / (1 + lambda) (m/s^2), piecewise constant in x."""

    def __init__(self, line: Line, rotary_allowance: float):
        bounds: list[float] = []
        values: list[float] = [0.0]
        k = 1.0 / (1.0 + rotary_allowance)
        for sec in sorted(line.gradients, key=lambda s: s.start):
            p = sec.permille / 1000.0
            acc = k * G * p / math.sqrt(1.0 + p * p)  # sin(atan(p)), as Line.gradient_accel
            if bounds and abs(bounds[-1] - sec.start) < 1e-12:
                values[-1] = acc
            else:
                bounds.append(sec.start)
                values.append(acc)
            bounds.append(sec.end)
            values.append(0.0)
        self.bounds = bounds
        self.values = values

    def __call__(self, x: float) -> float:
        return self.values[bisect_right(self.bounds, x)]


@dataclass
class MotionState:
    x: float  # m, position of the train's reference end along the track
    v: float  # m/s, speed (>= 0)
    stopped: bool  # held at rest (v == 0)


class Dynamics:
    """RK4 integrator of the true train on the true line (scalar state, lean inner loop)."""

    def __init__(self, train: TrainParams, line: Line, believed_train: TrainParams | None = None,
                 p_spec: float | None = None,
                 adhesion: tuple[float, float, float] | None = None,
                 drive_hook=None, resist_hook=None):
        """``p_spec``: power limit (m^2/s^3); ``adhesion``: (start m, end m, factor -) of a
        low-adhesion section (module docstring). Both None: the nominal drive.

        Hooks for effects defined elsewhere (the simulator's test effects): ``drive_hook(t, x,
        v, a_tr, a_br) -> (a_tr, a_br)`` (m/s^2) changes the delivered traction and braking parts
        (``t``: the step's mid time, as below);
        ``resist_hook(t, x, v)`` is an extra deceleration (m/s^2) at the step's mid time ``t``
        (set in ``self.t`` by the caller)."""
        m_eff = train.effective_mass
        self.ra = train.davis.a / m_eff  # m/s^2
        self.rb = train.davis.b / m_eff  # 1/s
        self.rc = train.davis.c / m_eff  # 1/m
        self.static = self.ra  # m/s^2, static resistance a / ((1+lambda) M) to break away
        believed = believed_train if believed_train is not None else train
        self.kappa = believed.effective_mass / m_eff
        self.grad = GradientLookup(line, train.rotary_allowance)
        self.p_spec = None if p_spec is None else float(p_spec)
        self.adhesion = None if adhesion is None else tuple(float(a) for a in adhesion)
        self.drive_hook, self.resist_hook = drive_hook, resist_hook
        self.t = 0.0  # s, mid time of the current step (for resist_hook)
        self.split = (self.p_spec is not None or self.adhesion is not None
                      or drive_hook is not None or resist_hook is not None)

    def drive(self, x: float, v: float, a_hat: float, a_br: float) -> float:
        """m/s^2, the control acceleration delivered (before kappa) for the actuator output
        a_hat with braking part a_br, at position x and speed v (module docstring)."""
        a_tr = a_hat - a_br
        p = self.p_spec
        if p is not None and a_tr > 0.0 and a_tr * v > p:
            a_tr = p / v
        ad = self.adhesion
        if ad is not None and ad[0] <= x < ad[1]:
            a_br = ad[2] * a_br
        if self.drive_hook is not None:
            a_tr, a_br = self.drive_hook(self.t, x, v, a_tr, a_br)
        return a_tr + a_br

    def _accel_hooked(self, x: float, v: float, a_hat: float) -> float:
        out = self.accel(x, v, a_hat)
        if self.resist_hook is not None:
            out -= self.resist_hook(self.t, x, max(v, 0.0))
        return out

    def _rk4_split(self, x, v, a0, a_mid, a_end, b0, b_mid, b_end, h):
        """RK4 as :meth:`_rk4` with the delivered drive (power limit, adhesion) at each stage."""
        d, f = self.drive, self._accel_hooked
        h2 = 0.5 * h
        k1 = f(x, v, d(x, v, a0, b0))
        x2, v2 = x + h2 * v, v + h2 * k1
        k2 = f(x2, v2, d(x2, v2, a_mid, b_mid))
        x3, v3 = x + h2 * v2, v + h2 * k2
        k3 = f(x3, v3, d(x3, v3, a_mid, b_mid))
        x4, v4 = x + h * v3, v + h * k3
        k4 = f(x4, v4, d(x4, v4, a_end, b_end))
        return (x + h * (v + 2.0 * v2 + 2.0 * v3 + v4) / 6.0,
                v + h * (k1 + 2.0 * k2 + 2.0 * k3 + k4) / 6.0)

    def accel(self, x: float, v: float, a_hat: float) -> float:
        """dv/dt of a moving train (v >= 0); resistance evaluated at max(v, 0)."""
        if v < 0.0:
            v = 0.0
        return self.kappa * a_hat - (self.ra + (self.rb + self.rc * v) * v) - self.grad(x)

    def can_start(self, x: float, a_hat: float) -> bool:
        """Breakaway test for a train at rest: forward force beats static resistance."""
        return self.kappa * a_hat - self.grad(x) > self.static

    def _rk4(self, x, v, a0, a_mid, a_end, h):
        f = self.accel
        h2 = 0.5 * h
        k1 = f(x, v, a0)
        v2 = v + h2 * k1
        k2 = f(x + h2 * v, v2, a_mid)
        v3 = v + h2 * k2
        k3 = f(x + h2 * v2, v3, a_mid)
        v4 = v + h * k3
        k4 = f(x + h * v3, v4, a_end)
        return (x + h * (v + 2.0 * v2 + 2.0 * v3 + v4) / 6.0,
                v + h * (k1 + 2.0 * k2 + 2.0 * k3 + k4) / 6.0)

    def step(self, s: MotionState, h: float, a0: float, a_mid: float, a_end: float,
             ue: float, tau: float, br: tuple | None = None) -> None:
        """Advance ``s`` by ``h`` given the actuator's a_hat at t, t + h/2, t + h.

        ``ue`` and ``tau`` describe the lag's closed form a_hat(t + r) = ue + (a0 - ue) e^{-r/tau},
        used when the step has to be cut at the stopping instant. ``br`` = (b0, b_mid, b_end, ub):
        the braking part of a_hat at the same times and its lag input (needed when
        ``self.split``: a power limit or an adhesion section).
        """
        split = self.split and br is not None
        if s.stopped:
            # Held at rest; release when the forward force at the step start beats static
            # resistance (10 ms resolution on the breakaway instant).
            if not self.can_start(s.x, self.drive(s.x, 0.0, a0, br[0]) if split else a0):
                return
            s.stopped = False
        if split:
            b0, b_mid, b_end, ub = br
            x1, v1 = self._rk4_split(s.x, s.v, a0, a_mid, a_end, b0, b_mid, b_end, h)
        else:
            x1, v1 = self._rk4(s.x, s.v, a0, a_mid, a_end, h)
        if v1 > 0.0:
            s.x, s.v = x1, v1
            return
        # v reaches 0 inside the step: find the stopping instant r in (0, h] by secant iteration
        # on v(r) of the RK4 solution (v is nearly linear over 10 ms), then stop there.
        v0 = s.v
        if v0 <= 0.0:  # was at rest and could not really start
            s.v, s.stopped = 0.0, True
            return
        lo, vlo, hi, vhi = 0.0, v0, h, v1
        xr = s.x
        for _ in range(4):
            r = lo + (hi - lo) * vlo / (vlo - vhi)
            r = min(max(r, 1e-12), h)
            er = math.exp(-0.5 * r / tau)
            am = ue + (a0 - ue) * er
            ae = ue + (am - ue) * er
            if split:
                bm = ub + (b0 - ub) * er
                xr, vr = self._rk4_split(s.x, v0, a0, am, ae, b0, bm, ub + (bm - ub) * er, r)
            else:
                xr, vr = self._rk4(s.x, v0, a0, am, ae, r)
            if abs(vr) < 1e-10:
                break
            if vr > 0.0:
                lo, vlo = r, vr
            else:
                hi, vhi = r, vr
        s.x, s.v, s.stopped = xr, 0.0, True
