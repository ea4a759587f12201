"""``traction_delay``: traction commands take effect later than train.yaml's delay; braking
does not (the two chains, train_core actuator.py).

The counterpart of ``brake_delay``: the extra traction delay d > 0 is profiled jointly with the
common command-time offset s (a nuisance: the link's mean latency moves both chains). Hypothesis
(s, d): traction re-timed by s + d, braking by s. The re-timed traction columns (believed
traction through the actuator at each offset, minus the believed one) are built once per run;
every (s, d) is a fixed combination of them and of the motion model's braking columns, scored
on one filter run (``drive.Candidates``). With a power limit in the null the re-timed traction
is capped at p_spec / v (a delayed command still meets the limit: at a power-limited release the
traction that goes on for the delay is p_spec / v, not the command)."""

from __future__ import annotations

import weakref

import numpy as np
from train_core.effects import TractionDelayEffect

from .base import Cause, resolved
from .drive import (
    Candidates,
    capped,
    delay_profile,
    envelope,
    traction_at,
    untestable_without_traction,
)

MIN_TRACTION = 0.05  # m/s^2, as power_limit: a traction command that can show a delay
_COLUMNS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()  # Motion -> {p_spec: columns}


class TractionDelay(Cause):
    name = "traction_delay"
    halves = ("delay",)

    def nominal(self, mo) -> dict:
        return {"delay": mo.train.brake.delay}
    family = "motion"

    def untestable(self, run, cfg, own) -> str | None:
        return untestable_without_traction(run, cfg, MIN_TRACTION)

    def fit(self, st) -> tuple:
        """Profile over (s, d > 0) on the grids of brake_delay; the delay refined by a parabola
        fitted to the profile likelihood of d around its best (:func:`.drive.envelope`)."""
        mo = st.mo
        keys, cols = _columns(mo, st.null.p_spec)
        cand = Candidates(st, drift=cols)
        base = _fixed(cand.k, keys, st.null.shift, st.null.brake_extra, -1.0)
        prof = {}
        for s in mo.shifts:
            for d in mo.delays:
                if d <= 0.0:
                    continue
                u = base + _fixed(cand.k, keys, float(s), st.null.brake_extra, 1.0, float(d))
                prof[(float(s), float(d))] = cand.dll(cand.quad_fixed(u))
        (s_b, d_b), dll = max(prof.items(), key=lambda kv: kv[1])
        ds, lls, _ = delay_profile(prof)  # the offset maximised out at each d
        d_hat, se = envelope(ds, lls, ds.index(d_b))
        return st.null_ll() + dll, 1, {"delay": mo.train.brake.delay + d_hat}, {"delay": se}, \
            {"offset": s_b, "extra": d_b, "profile": list(zip(ds, lls))}

    def resolution(self, fit, mo) -> str | None:
        """As a brake delay: a traction delay change below one odometer period is not a delay
        the samples can show (the believed traction delay is the actuator's delay)."""
        t = mo.ev.t[mo.ev.odo]
        period = float(np.median(np.diff(t))) if t.size > 1 else 0.0
        return resolved("delay", fit.parameters["delay"] - mo.train.brake.delay,
                        fit.std_errors.get("delay"), period, " s")

    def extend_null(self, null, fit, mo) -> None:
        """The common offset is the fit's; traction moves by the extra delay beyond it."""
        keys, (bv, bs) = _columns(mo, null.p_spec)
        s, d = fit.extra["offset"], fit.extra["extra"]
        w = np.zeros(len(keys))
        for key, c in ((s + d, 1.0), (s, -1.0)):
            k = round(key, 6)
            if ("T", k) in keys:
                w[keys[("T", k)]] += c
        null.shift = s
        null.traction_timing = s + d
        null.extra.append((bv @ w, bs @ w))

    def replay_offset(self, extra: dict, shift: float) -> float:
        # a traction delay is fitted with its own offset: the pair is the extension's timing
        return extra["offset"]

    def effect(self, params: dict, duration: float) -> TractionDelayEffect:
        return TractionDelayEffect(float(params["delay"]))


def _columns(mo, p_spec: float | None = None) -> tuple[dict, tuple]:
    """Columns [traction re-timed by every offset s + d (the believed one subtracted), the
    motion model's braking columns]: ({("T" or "B", key): column index}, (Bv, Bs)). With
    ``p_spec`` both the re-timed and the believed traction are capped at p_spec / v (the
    null's power limit), so that a hypothesis replaces the null's capped traction by the capped
    re-timed one."""
    cache = _COLUMNS.setdefault(mo, {})
    ck = None if p_spec is None else round(float(p_spec), 9)
    if ck in cache:
        return cache[ck]
    keys = sorted({round(float(s + d), 6) for s in mo.shifts for d in mo.delays} - {0.0})
    a0 = capped(mo, mo.a_tr0, p_spec)
    R = np.stack([(capped(mo, traction_at(mo, k), p_spec) - a0) * mo.moving
                  for k in keys]).T  # rows stacked: Grid.integrate
    Bv, Bs = mo.grid.integrate(R, mo.ev.t.size)
    index = {("T", k): i for i, k in enumerate(keys)}
    bk = sorted(mo.braking_cols)
    for k in bk:
        index[("B", k)] = len(index)
    cols = [mo.col[mo.braking_cols[k]] for k in bk]
    out = (index, (np.concatenate([Bv, mo.Dv[:, cols]], axis=1),
                   np.concatenate([Bs, mo.Ds[:, cols]], axis=1)))
    cache[ck] = out
    return out


def _fixed(k: int, keys: dict, shift: float, brake_extra: float, sign: float,
           traction_extra: float = 0.0) -> np.ndarray:
    """The combination (over [fixed, s0, columns]) that moves traction to shift +
    traction_extra and braking to shift + brake_extra, times ``sign`` (-1: undo the null's)."""
    u = np.zeros(k + 2)
    if sign > 0:
        u[0] = 1.0
    for kind, key in (("T", shift + traction_extra), ("B", shift + brake_extra)):
        j = keys.get((kind, round(key, 6)))
        if j is not None:
            u[2 + j] += sign
    return u


CAUSE = TractionDelay()
