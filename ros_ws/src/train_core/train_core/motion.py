"""The train's motion under its actuator: the one integration loop of the project.

:class:`Motion` advances the true train on the true line (``dynamics.Dynamics``, RK4 with the
standstill rule) driven by an :class:`~train_core.actuator.Actuator` whose input is constant
between the caller's event times. The simulator's :class:`train_sim.world.World` steps it between
its events (ATO cycles, samples, actuator switches) and reads the axle and the balises in its
``visit`` hook; :func:`replay` drives it with a recorded command series (open loop, no sensors),
which is how ``diagnose`` predicts the speed a model gives for the commands a train received.

Pure module: the standard library and numpy.
"""

from __future__ import annotations

import math
from bisect import bisect_right
from collections.abc import Callable

import numpy as np

from .actuator import Actuator
from .dynamics import Dynamics, MotionState
from .model import Line, TrainParams

_EPS = 1e-9  # s


class Motion:
    """True motion of one train; ``braking_rate_of_t(t)`` is the true braking rate (s -> -)."""

    def __init__(self, train: TrainParams, line: Line, believed: TrainParams, act: Actuator,
                 x0: float, v0: float, max_step: float = 0.01,
                 braking_rate_of_t: Callable[[float], float] | None = None,
                 p_spec: float | None = None,
                 adhesion: tuple[float, float, float] | None = None,
                 drive_hook=None, resist_hook=None):
        """``p_spec``, ``adhesion``: a power limit and a low-adhesion section on the delivered
        drive; ``drive_hook``, ``resist_hook``: further effects (dynamics.py); None = off."""
        self.act = act
        self.dyn = Dynamics(train, line, believed, p_spec, adhesion, drive_hook, resist_hook)
        self.state = MotionState(float(x0), float(v0), v0 == 0.0)
        self.max_step = float(max_step)
        self.braking_rate_const = train.brake.braking_rate if braking_rate_of_t is None else None
        self.braking_rate_of_t = braking_rate_of_t
        self.t = act.t

    def integrate(self, t_next: float,
                  visit: Callable[[float, float, float, float], None] | None = None) -> None:
        """Advance to ``t_next`` in equal RK4 steps <= max_step; the actuator's delayed input
        must not change inside (t, t_next) (the caller cuts at ``act.next_switch()``).
        ``visit(t0, h, x0, x1)`` is called after every step in which the train moved."""
        t_start = self.t
        span = t_next - t_start
        n = max(1, math.ceil(span / self.max_step - 1e-9))
        h = span / n
        act, dyn, st = self.act, self.dyn, self.state
        tau = act.tau
        braking_rate_const = self.braking_rate_const
        split = dyn.split
        act.track_br = split
        if split:  # the delivered drive's effects at each stage
            for i in range(n):
                t0 = t_start + i * h
                f = braking_rate_const if braking_rate_const is not None else \
                    self.braking_rate_of_t(t0 + 0.5 * h)
                ue = act.effective(f)  # constant over the span (ends at the next input change)
                ub = f * act.u_br
                a0, a_mid, a_end = act.segment(h, f)
                x0 = st.x
                dyn.t = t0 + 0.5 * h
                dyn.step(st, h, a0, a_mid, a_end, ue, tau, (*act.br_stages, ub))
                if visit is not None and st.x > x0:
                    visit(t0, h, x0, st.x)
        else:
            self._integrate_plain(t_start, n, h, visit)
        self.t = t_next
        act.t = t_next  # no round-off drift between the actuator and the caller's clock
        act._activate()

    def _integrate_plain(self, t_start: float, n: int, h: float, visit) -> None:
        """:meth:`integrate`'s loop for the nominal drive (no power limit, adhesion section or
        hook): ``Actuator.segment``, ``Dynamics.step``'s RK4 and ``Dynamics.accel`` written out
        with the same operations in the same order, so the same floats (the simulator and the
        driver's pilot runs spent about half of their time in those calls). A step that starts
        at rest or ends in a stop goes through ``Dynamics.step``, which recomputes the same RK4
        and cuts it at the stopping instant."""
        act, dyn, st = self.act, self.dyn, self.state
        tau = act.tau
        f_const, f_of = self.braking_rate_const, self.braking_rate_of_t
        e = math.exp(-0.5 * h / tau)  # (Actuator.segment's factor: h and tau fixed here)
        kappa, ra, rb, rc, static = dyn.kappa, dyn.ra, dyn.rb, dyn.rc, dyn.static
        bounds, values = dyn.grad.bounds, dyn.grad.values
        pipe, bpipe = act._pipe, act._bpipe
        h2 = 0.5 * h
        inf = math.inf
        # the next activation time (the earlier pipe head), and with a constant f the input
        # ue, which only an activation changes (from the next step on): both kept between
        # steps, not recomputed
        due = min(pipe[0][0] if pipe else inf, bpipe[0][0] if bpipe else inf)
        stale = True  # ue to be computed
        for i in range(n):
            t0 = t_start + i * h
            if f_const is None:
                ue = act.u_tr + f_of(t0 + 0.5 * h) * act.u_br  # Actuator.effective
            elif stale:
                ue = act.u_tr + f_const * act.u_br
                stale = False
            a0 = act.a  # Actuator.segment (its braking part untracked: track_br False)
            a_mid = ue + (a0 - ue) * e
            a_end = ue + (a_mid - ue) * e
            act.a = a_end
            act.t += h
            if due <= act.t + _EPS:
                act._activate()
                due = min(pipe[0][0] if pipe else inf, bpipe[0][0] if bpipe else inf)
                stale = True
            x = x0 = st.x
            if st.stopped:
                # held at rest unless Dynamics.can_start (a step that only tests it, often the
                # most common kind: a dwell, the end of a run)
                if kappa * a0 - values[bisect_right(bounds, x)] > static:
                    dyn.step(st, h, a0, a_mid, a_end, ue, tau)
            else:
                # Dynamics._rk4 with Dynamics.accel at its four stages (v >= 0 as there)
                v = st.v
                w = 0.0 if v < 0.0 else v
                k1 = kappa * a0 - (ra + (rb + rc * w) * w) - values[bisect_right(bounds, x)]
                v2 = v + h2 * k1
                w = 0.0 if v2 < 0.0 else v2
                k2 = kappa * a_mid - (ra + (rb + rc * w) * w) - \
                    values[bisect_right(bounds, x + h2 * v)]
                v3 = v + h2 * k2
                w = 0.0 if v3 < 0.0 else v3
                k3 = kappa * a_mid - (ra + (rb + rc * w) * w) - \
                    values[bisect_right(bounds, x + h2 * v2)]
                v4 = v + h * k3
                w = 0.0 if v4 < 0.0 else v4
                k4 = kappa * a_end - (ra + (rb + rc * w) * w) - \
                    values[bisect_right(bounds, x + h * v3)]
                v1 = v + h * (k1 + 2.0 * k2 + 2.0 * k3 + k4) / 6.0
                if v1 > 0.0:
                    st.x, st.v = x + h * (v + 2.0 * v2 + 2.0 * v3 + v4) / 6.0, v1
                else:
                    dyn.step(st, h, a0, a_mid, a_end, ue, tau)
            if visit is not None and st.x > x0:
                visit(t0, h, x0, st.x)

    @property
    def drive_acceleration(self) -> float:
        """m/s^2, kappa a_hat: the control acceleration on the true train (as delivered, after
        a power limit or an adhesion section)."""
        dyn, act = self.dyn, self.act
        if dyn.split:
            st = self.state
            return dyn.kappa * dyn.drive(st.x, st.v, act.a, act.a_br)
        return dyn.kappa * act.a


WARMUP = 30.0  # s, the actuator's warm-up before a replay's start (warm_actuator's default)


def _actuator(train: TrainParams, warmup: float, brake_delay: float | None,
              traction_delay: float | None) -> Actuator:
    """The actuator a replay starts from, ``warmup`` s before its start (the two chains'
    delays: the train's where None)."""
    return Actuator(train.brake.time_constant,
                    train.brake.delay if traction_delay is None else traction_delay, t0=-warmup,
                    brake_delay=train.brake.delay if brake_delay is None else brake_delay)


def _warm_commands(t_cmd: np.ndarray, a_cmd: np.ndarray, t0: float, warmup: float) -> tuple:
    """The commands issued before ``t0`` that the warm-up visits, times relative to ``t0``: of
    a run of consecutive commands long before (earlier than ``warmup`` s), only its last one
    leaves a trace (each overwrites the parts in force), so the others are left out (a replay
    late in a long run would walk every earlier command); the state is the same."""
    before = t_cmd < t0
    t_b, a_b = t_cmd[before] - t0, a_cmd[before]
    early = t_b < -warmup
    keep = ~early
    keep[:-1] |= early[:-1] & ~early[1:]
    keep[-1:] |= early[-1:]
    return t_b[keep], a_b[keep]


def warm_actuator(train: TrainParams, t_cmd, a_cmd, t0: float, warmup: float = WARMUP,
                  brake_delay: float | None = None,
                  braking_rate_of_t: Callable[[float], float] | None = None,
                  traction_delay: float | None = None) -> Actuator:
    """The actuator's state at ``t0`` from the commands issued before it (the delay lines
    filled, the lag run over ``warmup`` s: the unknown earlier output is forgotten to within
    exp(-warmup / tau)). Times in the returned actuator are shifted so that t0 -> 0.
    ``brake_delay``/``traction_delay``: the two chains' delays (default: the train's delay)."""
    f_of = braking_rate_of_t or (lambda t: train.brake.braking_rate)
    act = _actuator(train, warmup, brake_delay, traction_delay)
    act.track_br = True  # the braking part too, for a Motion with drive effects
    t_w, a_w = _warm_commands(np.asarray(t_cmd, dtype=float), np.asarray(a_cmd, dtype=float),
                              t0, warmup)
    for t_i, a_i in zip(t_w, a_w):
        if t_i >= -warmup:
            act.advance(t_i, f_of(t_i + t0))
            act.command(t_i, a_i)
        else:  # long before: only the latest such command is still in force
            act.u_tr, act.u_br = max(a_i, 0.0), min(a_i, 0.0)
    act.advance(0.0, f_of(t0))
    act.t = 0.0
    return act


def replay(line: Line, train: TrainParams, t_cmd, a_cmd, t0: float, t_out,
           x0: float, v0: float, believed: TrainParams | None = None,
           brake_delay: float | None = None,
           braking_rate_of_t: Callable[[float], float] | None = None,
           max_step: float = 0.01, traction_delay: float | None = None,
           p_spec: float | None = None,
           adhesion: tuple[float, float, float] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Open-loop motion from (x0, v0) at ``t0`` under the recorded commands (t_cmd, a_cmd):
    position and speed at the times ``t_out`` (>= t0, increasing). ``train`` is the true train
    (its braking rate unless ``braking_rate_of_t`` is given), ``believed`` the one the controller
    makes
    forces for (default ``train``), ``brake_delay`` the braking chain's delay (default the
    train's delay), ``traction_delay`` the traction chain's (default the train's delay),
    ``p_spec``/``adhesion`` a power limit and a low-adhesion section (dynamics.py).

    With a constant braking rate the loop runs compiled (:mod:`train_core.replay_loop`: the
    same operations, the same floats) where numba or its ahead-of-time build is there."""
    t_cmd = np.asarray(t_cmd, dtype=float)
    a_cmd = np.asarray(a_cmd, dtype=float)
    if braking_rate_of_t is None:
        out = _replay_compiled(line, train, t_cmd, a_cmd, t0, t_out, x0, v0, believed,
                               brake_delay, max_step, traction_delay, p_spec, adhesion)
        if out is not None:
            return out
    return _replay_python(line, train, t_cmd, a_cmd, t0, t_out, x0, v0, believed, brake_delay,
                          braking_rate_of_t, max_step, traction_delay, p_spec, adhesion)


def _replay_python(line, train, t_cmd, a_cmd, t0, t_out, x0, v0, believed, brake_delay,
                   braking_rate_of_t, max_step, traction_delay, p_spec, adhesion):
    """:func:`replay`'s loop, interpreted."""
    shifted_f = None if braking_rate_of_t is None else (lambda t: braking_rate_of_t(t + t0))
    act = warm_actuator(train, t_cmd, a_cmd, t0, brake_delay=brake_delay,
                        braking_rate_of_t=braking_rate_of_t, traction_delay=traction_delay)
    mot = Motion(train, line, believed or train, act, x0, v0, max_step, shifted_f, p_spec,
                 adhesion)
    after = t_cmd >= t0
    cmds = list(zip((t_cmd[after] - t0).tolist(), a_cmd[after].tolist()))
    t_rel = np.asarray(t_out, dtype=float) - t0
    xs = np.empty(t_rel.size)
    vs = np.empty(t_rel.size)
    k = 0
    for i, tr in enumerate(t_rel):
        while True:
            t_c = cmds[k][0] if k < len(cmds) else math.inf
            t_next = min(tr, t_c, act.next_switch())
            if t_next > mot.t + _EPS:
                mot.integrate(t_next)
            if k < len(cmds) and cmds[k][0] <= mot.t + _EPS:
                act.command(mot.t, cmds[k][1])
                k += 1
                continue
            if mot.t >= tr - _EPS:
                break
        xs[i], vs[i] = mot.state.x, mot.state.v
    return xs, vs



def _replay_compiled(line, train, t_cmd, a_cmd, t0, t_out, x0, v0, believed, brake_delay,
                     max_step, traction_delay, p_spec, adhesion):
    """:func:`replay` through :mod:`train_core.replay_loop`'s compiled loop (a constant braking
    rate): warm_actuator's choice of commands, the actuator's and the dynamics' parameters as
    their constructors make them; None without the compiled loop, for commands out of time
    order (the interpreted replay raises) or parameters the constructors refuse."""
    from . import replay_loop

    kern = replay_loop.kernel()
    if kern is None:
        return None
    try:
        act = _actuator(train, WARMUP, brake_delay, traction_delay)
        dyn = Dynamics(train, line, believed or train, p_spec, adhesion)
    except ValueError:
        return None
    t_w, a_w = _warm_commands(t_cmd, a_cmd, t0, WARMUP)  # warm_actuator's commands
    after = t_cmd >= t0
    t_rel = np.asarray(t_out, dtype=float) - t0
    ad = dyn.adhesion
    D = np.array([dyn.kappa, dyn.ra, dyn.rb, dyn.rc, dyn.static,
                  0.0 if dyn.p_spec is None else dyn.p_spec, float(dyn.p_spec is not None),
                  *(ad if ad is not None else (0.0, 0.0, 0.0)), float(ad is not None)])
    xs, vs = np.empty(t_rel.size), np.empty(t_rel.size)
    c = np.ascontiguousarray
    rc = kern(c(t_w), c(a_w), c(t_cmd[after] - t0), c(a_cmd[after]), c(t_rel),
              float(x0), float(v0), float(train.brake.braking_rate), act.tau, act.delay,
              act.brake_delay, WARMUP, D, np.array(dyn.grad.bounds, dtype=float),
              np.array(dyn.grad.values, dtype=float), float(max_step), xs, vs)
    return (xs, vs) if rc == 0 else None
