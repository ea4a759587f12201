"""Driver / ATO: runs a timetable over the line with the braking it *believes* in.

Every ``control_period`` the ATO reads the train's position and speed (it is assumed perfectly
localised, so stopping errors isolate the braking model) and issues a target acceleration
a_Tar (> 0 traction, < 0 braking). It knows only the believed train (``train.yaml``) and line
(``line.yaml``) and its own belief ``f_b`` of the braking rate (nominal 1; a benchmark may feed it
an estimate through :meth:`Driver.set_braking_rate_belief`).

Dead-time compensation. The actuator delays a command by T and lags it by tau, so the ATO acts on
a *predicted* state (x_p, v_p) at t + H, H = T_b + tau_b + control_period, obtained by running its
believed actuator (the commands already in the delay line, f_b) and the believed dynamics forward.

Braking curve. The plan deceleration is a_plan = margin * f_b * a_service (a service-brake command
is believed to deliver f_b * a_service; ``margin`` < 1 leaves feedback authority). With d_p the
distance from x_p to the stopping point s, the deceleration still needed is

    a_req = v_p^2 / (2 d_p)          (constant deceleration to go; self-correcting: if the train
                                       brakes less than planned, d_p shrinks faster than v_p^2)

Braking starts when a_req >= a_plan (the target speed sqrt(2 a_plan d_p) is reached) and then
commands the a_hat giving a net deceleration a_req under the believed resistance and gradient,
a_Tar = a_hat / f_b, limited to the service brake. Once the predicted stop falls inside the
horizon (v_p = 0) the command is frozen: on the curve it is already constant, and the frozen
command stops the train at s. With the true f equal to f_b stops are within a few centimetres;
with f < f_b the service-brake limit is reached and the train overshoots: the stopping error.

Cruise: a_hat = K (v_target - v_p) + believed resistance and gradient, with v_target the lowest
of the speed limit at x and x_p minus ``speed_margin``, the movement authority's permitted speed,
braking curves to lower limits ahead and sqrt(2 a_plan d_p) to the stopping point.

Movement authority: the stopping point is min(next station, end_of_authority - ma_margin); a stop
short of a station because of the authority is not a station stop, the train waits. Emergency
brake: a_Tar = -emergency_brake (through the same actuator) while the flag is set; every rising
edge is counted, and those before the first authority without it (the start-up state of a train
no zone controller has localised yet) are also counted apart as ``startup_emergency_brakes``. A
brake released while the train dwells at rest stays applied until the dwell ends: the moment a
release reaches the train (a radio message, racing a wall clock in the live simulator) then
changes nothing it does. At rest the ATO holds the train with a_Tar = -hold_brake.

Pure module: the standard library and the shared model only.
"""

from __future__ import annotations

import bisect
import math
from dataclasses import dataclass

from train_core.actuator import _EPS, Actuator
from train_core.dynamics import GradientLookup
from train_core.model import Line, TrainParams

DRIVER_MODES = ("ato", "open_loop")


@dataclass(frozen=True)
class TimetableStop:
    station: str  # name of the station in line.yaml
    position: float  # m, stopping point
    dwell: float  # s, dwell time


@dataclass(frozen=True)
class DriverParams:
    mode: str = "ato"  # "ato" (timetable) or "open_loop" (a_Tar profile)
    control_period: float = 0.1  # s, ATO cycle
    braking_rate_belief: float = 1.0  # -, f the ATO plans with
    brake_margin: float = 0.85  # -, a_plan = margin * f_b * service_brake
    speed_margin: float = 0.5  # m/s, cruise below the limit by this much
    speed_gain: float = 0.0  # 1/s, cruise feedback gain K; 0 = automatic 0.5 / H
    stop_tolerance: float = 1.0  # m, at rest closer than this (or beyond) = arrived
    ma_margin: float = 5.0  # m, aim to stop this far before the end of authority
    hold_brake: float = 0.3  # m/s^2, holding brake command magnitude at rest
    initial_dwell: float = 0.0  # s, wait at the start before departing
    profile: tuple[tuple[float, float], ...] = ()  # open_loop: ((t s, a_Tar m/s^2), ...)


class Driver:
    """The ATO. Call :meth:`update` every control period with the train's state."""

    def __init__(self, line: Line, train: TrainParams, params: DriverParams,
                 timetable: tuple[TimetableStop, ...], start_position: float,
                 start_speed: float = 0.0, t0: float = 0.0, a0: float = 0.0, u0: float = 0.0):
        self.line, self.train, self.p = line, train, params
        b = train.brake
        self._act = Actuator(b.time_constant, b.delay, a0=a0, u0=u0, t0=t0)  # believed actuator
        self.braking_rate_belief = float(params.braking_rate_belief)
        self.horizon = b.delay + b.time_constant + params.control_period
        self.gain = params.speed_gain or 0.5 / self.horizon
        m_eff = train.effective_mass
        self._ra, self._rb, self._rc = (train.davis.a / m_eff, train.davis.b / m_eff,
                                        train.davis.c / m_eff)
        self._grad = GradientLookup(line, train.rotary_allowance)
        self.eoa = math.inf  # m
        self.permitted_speed = math.inf  # m/s
        self.emergency = False
        self.emergency_brakes = 0
        self.startup_emergency_brakes = 0  # rising edges before the first authority without one
        self.authorised = False  # an authority without the emergency brake has been received
        self._eb_applied = False  # the brake is still on (released at rest: until departure)
        self.stops: list[dict] = []
        self.queue = [s for s in timetable if s.position > start_position + params.stop_tolerance]
        self.a_cmd = float(u0)
        self.braking = False
        if start_speed > 0.0:
            self.mode, self.dwell_end = "run", t0
        else:
            self.mode, self.dwell_end = "dwell", t0 + params.initial_dwell
        self._profile = sorted(params.profile)
        self._profile_t = [ti for ti, _ in self._profile]  # for bisection in _decide

    # -- inputs from outside ---------------------------------------------------------------------
    def set_braking_rate_belief(self, braking_rate: float) -> None:
        """Plan with ``braking_rate`` (e.g. an online estimate) instead of the nominal one."""
        if not (math.isfinite(braking_rate) and braking_rate > 0.0):
            raise ValueError(f"braking rate belief must be finite and > 0, got {braking_rate!r}")
        self.braking_rate_belief = float(braking_rate)

    def set_movement_authority(self, end_of_authority: float, permitted_speed: float,
                               emergency_brake: bool) -> str:
        """Take the zone controller's authority; "" or why its end or speed was refused
        (``name: detail``).

        An end of authority that is NaN (+-inf are the open line and none) or a permitted speed
        that is NaN or negative says nothing the train can stop at: the authority in force is
        kept (one such message stopped the train where it was, for good). An emergency brake
        is applied whatever its other fields say: it is the safe side."""
        why = ("non_finite: end_of_authority is NaN" if math.isnan(end_of_authority)
               else "" if permitted_speed >= 0.0 else
               f"bad_speed: permitted_speed {permitted_speed!r} is not >= 0")
        if why and not emergency_brake:
            return why
        if emergency_brake and not self.emergency:
            self.emergency_brakes += 1
            self.startup_emergency_brakes += not self.authorised
        self.authorised |= not emergency_brake
        self.emergency = bool(emergency_brake)
        if not why:
            self.eoa = float(end_of_authority)
            self.permitted_speed = float(permitted_speed)
        return why

    # -- the control law -------------------------------------------------------------------------
    def update(self, t: float, x: float, v: float, stopped: bool) -> float:
        """a_Tar (m/s^2) to issue at time ``t`` given position ``x`` and speed ``v``."""
        self._act.advance(t, self.braking_rate_belief)
        a = self._decide(t, x, v, stopped)
        self._act.command(t, a)
        self.a_cmd = a
        return a

    def _resist(self, x: float, v: float) -> float:
        """Believed resistance + gradient deceleration at (x, v), m/s^2."""
        return self._ra + (self._rb + self._rc * v) * v + self._grad(x)

    def _to_command(self, a_hat: float) -> float:
        perf = self.train.performance
        if a_hat >= 0.0:
            return min(a_hat, perf.max_traction)
        return max(a_hat / self.braking_rate_belief, -perf.service_brake)

    def _predict(self, x: float, v: float) -> tuple[float, float]:
        """Believed (x, v) at t + H: delay line and lag exact, motion by trapezoid steps.

        The believed actuator is run forward on local copies of its state, not stepped:
        ``Actuator.advance``, ``segment`` and ``_activate`` and :meth:`_resist` written out with
        the same operations in the same order, so the same floats (the calls cost three times
        the loop itself)."""
        act = self._act
        f, tau = self.braking_rate_belief, act.tau
        t, a, u_tr, u_br = act.t, act.a, act.u_tr, act.u_br
        pipe, bpipe = act._pipe, act._bpipe  # read, not consumed: i, j are their heads
        ni, nj = len(pipe), len(bpipe)
        i = j = 0
        ra, rb, rc = self._ra, self._rb, self._rc
        bounds, values = self._grad.bounds, self._grad.values
        inf, exp = math.inf, math.exp
        n = max(3, math.ceil(self.horizon / 0.1))
        h = self.horizon / n
        for _ in range(n):
            a_start = a
            t_new = t + h
            while t < t_new - _EPS:  # Actuator.advance(t + h, f)
                ta = pipe[i][0] if i < ni else inf  # next_switch
                tb = bpipe[j][0] if j < nj else inf
                t_switch = ta if ta < tb else tb
                t_stop = t_switch if t_switch < t_new else t_new
                hs = t_stop - t  # segment(hs, f)
                ub = f * u_br
                ue = u_tr + ub
                e = exp(-0.5 * hs / tau)
                a_mid = ue + (a - ue) * e
                a = ue + (a_mid - ue) * e
                t_seg = t + hs + _EPS
                if t_switch <= t_seg or t_switch <= t_stop + _EPS:  # else neither pops
                    for te in (t_seg, t_stop + _EPS):  # _activate after t += hs, t = t_stop
                        while i < ni and pipe[i][0] <= te:
                            u_tr = pipe[i][1]
                            i += 1
                        while j < nj and bpipe[j][0] <= te:
                            u_br = bpipe[j][1]
                            j += 1
                t = t_stop
            dv = h * (0.5 * (a_start + a) - (ra + (rb + rc * v) * v + values[bisect.bisect_right(
                bounds, x)]))
            v_new = v + dv
            if v_new <= 0.0:  # stops inside this sub-step
                frac = v / (v - v_new) if v > v_new else 0.0
                return x + 0.5 * v * frac * h, 0.0
            x += 0.5 * h * (v + v_new)
            v = v_new
        return x, v

    def _target_speed(self, x: float, xp: float, dp: float, a_plan: float) -> float:
        line = self.line
        vt = min(line.speed_limit(x), line.speed_limit(xp), self.permitted_speed)
        for sl in line.speed_limits:  # braking curves to lower limits ahead
            if sl.start > x and sl.speed < vt:
                vt = min(vt, math.sqrt(sl.speed**2 + 2.0 * a_plan * max(sl.start - xp, 0.0)))
        vt -= self.p.speed_margin
        vt = min(vt, math.sqrt(2.0 * a_plan * max(dp, 0.0)))
        return max(vt, 0.0)

    def _decide(self, t: float, x: float, v: float, stopped: bool) -> float:
        p, perf = self.p, self.train.performance
        if self.emergency:
            self._eb_applied = True
            return -perf.emergency_brake
        if self._eb_applied:
            if stopped and self.mode == "dwell" and t + 1e-9 < self.dwell_end:
                return -perf.emergency_brake  # released during a dwell: applied until departure
            self._eb_applied = False
        if p.mode == "open_loop":
            # the last profile entry at or before t (bisection: a scan per cycle made open-loop
            # runs 8x slower than needed)
            k = bisect.bisect_right(self._profile_t, t + 1e-9) - 1
            return self._profile[k][1] if k >= 0 else self.a_cmd
        hold = -min(p.hold_brake, perf.service_brake)
        if self.mode == "dwell":
            if t + 1e-9 < self.dwell_end or not self.queue:
                return hold
            self.mode, self.braking = "run", False
        if self.mode == "finished":
            return hold
        st = self.queue[0]
        s_ma = self.eoa - p.ma_margin
        is_station = st.position <= s_ma
        s = st.position if is_station else s_ma
        if stopped:
            if s - x <= p.stop_tolerance:
                if is_station:
                    self.stops.append({"station": st.station, "position": st.position,
                                       "stop_position": x, "stopping_error": x - st.position,
                                       "t": t})
                    self.queue.pop(0)
                    self.mode = "dwell" if self.queue else "finished"
                    self.dwell_end = t + st.dwell
                return hold
            self.braking = False  # at rest short of the stopping point: re-plan and creep on
        xp, vp = self._predict(x, v)
        dp = s - xp
        a_plan = p.brake_margin * self.braking_rate_belief * perf.service_brake
        if vp > 0.0:
            a_req = vp * vp / (2.0 * dp) if dp > 0.0 else math.inf
            if self.braking and a_req < 0.5 * a_plan:
                self.braking = False  # target moved away (authority extended): cruise again
            if self.braking or a_req >= a_plan:
                self.braking = True
                return self._to_command(-a_req + self._resist(xp, vp))
        elif self.braking:
            return self.a_cmd  # predicted stop inside the horizon: freeze the command
        vt = self._target_speed(x, xp, dp, a_plan)
        return self._to_command(self.gain * (vt - vp) + self._resist(xp, vp))
