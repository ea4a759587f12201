"""The measured run and its preparation: order, clean, fit the clocks, put everything on one
time axis (docs/interfaces.md clocks).

Odometer and balise stamps are on the train's clock, control on the reference clock. The rate
and offset between them come from the odometer's (stamp, log time) pairs; control stamps are
mapped onto the train clock, and a residual common command-time offset (the link's mean latency)
is a nuisance parameter profiled with the brake timing (``stage``). Times in the report are
seconds since the first odometer stamp, on the stamp clock.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from train_core.model import Line

from train_estimation.core.offline.clock_fit import ClockFit

from ..measured import MeasuredRun, no_counter, unwrap, variances_unstated

LATENCY_FLOOR_Q = 0.01  # the quantile of the clock fit's residuals taken as the link's floor


class DiagnoseError(ValueError):
    """The data cannot be diagnosed (unusable input); the message is one line saying what is
    missing or wrong and what to do."""


@dataclass(frozen=True)
class DiagConfig:
    max_rate: float = 5.0  # Hz, odometer samples are decimated to at most this rate
    grid_dt: float = 0.02  # s, grid of the actuator and the regressor integrals
    min_duration: float = 120.0  # s, shorter runs are refused
    min_speed: float = 1.0  # m/s, the train must exceed this somewhere
    min_brake: float = 0.05  # m/s^2, |a_Tar| above this counts as braking
    standstill_speed: float = 1.0  # m/s, intervals reaching below this are not modelled
    standstill_q: float = 1.0  # (m/s^2)^2 s, process noise there (the filter follows data)
    # (m/s^2)^2 s, smallest process-noise PSD: a real train has unmodelled accelerations (wind,
    # adhesion, track) of a few mm/s^2; without a floor a noise-free simulator drives q to 0
    # and any small mismatch of timing or discretisation passes for a second cause
    q_floor: float = 1e-5
    gradient_bin: float = 25.0  # m, finest resolution of the gradient-section search
    max_bins: int = 240  # at most this many position bins (coarser bins on long runs)
    min_section: float = 100.0  # m, shortest gradient section considered
    shift_grid: tuple = (-0.2, 0.4, 0.025)  # s, command-time offsets (nuisance): lo, hi, step
    delay_grid: tuple = (0.0, 1.6, 0.025)  # s, extra braking delays tested: lo, hi, step
    slip_threshold: float = 3.0  # |standardised speed innovation| that opens a slip candidate
    max_slip_candidates: int = 8
    stages: int = 3  # greedy stages (causes put into the null one after the other)
    gain_block: float = 30.0  # s, alternating fit/held-out blocks for the gain
    gain_min_change: float = 0.05  # m/s, RMS change of a block's prediction that counts
    noise_refits: int = 2  # best causes of a stage whose score is recomputed at their own noise


@dataclass
class Run:
    """The run on one time axis: seconds since the first odometer sample on the reference
    clock (``odo_stamp``: the same on the train's clock, for the clock test and the report)."""

    t_first: float  # s, first odometer stamp (train clock)
    duration: float  # s
    odo_t: np.ndarray
    odo_stamp: np.ndarray
    odo_d: np.ndarray
    odo_v: np.ndarray
    odo_rv: np.ndarray
    odo_seq: np.ndarray  # unwrapped, int64
    odo_recv: np.ndarray
    ctrl_t: np.ndarray  # mapped onto the train clock
    ctrl_a: np.ndarray
    bal_t: np.ndarray
    bal_p: np.ndarray
    bal_r: np.ndarray
    bal_id: np.ndarray
    clock: dict
    notes: list


def _arr(x, dtype=float):
    return np.asarray(x if x is not None else [], dtype=dtype).ravel()


def prepare(data: MeasuredRun, line: Line, cfg: DiagConfig, train=None) -> Run:
    """The run on the reference clock's time axis; :class:`DiagnoseError` when unusable.
    ``train`` (the believed train): its variances stand in for a stream that states every
    variance as 0 (:func:`unstated`)."""
    notes = list(getattr(data, "notes", ()))
    _require_topics(data)
    # the train clock's steps and change of rate out of the stamps first (MeasuredRun)
    data, steps = data.without_clock_steps()
    data, change = data.without_rate_change()
    for at, jump, _ in steps:
        notes.append(f"the train's clock jumped by {jump:+.3f} s at stamp {at:.3f}: the "
                     "readings after it are put back on the clock before it")
    idx, fields, seq = _odometer(data, notes, train)
    odo_s, odo_r = _arr(data.odo_stamp), _arr(data.odo_recv)
    s_odo, r_odo = odo_s[idx], odo_r[idx]
    # ---- clock: log time r = alpha + beta * stamp + latency (OLS; latency mean in alpha) -----
    cf, kept = ClockFit.fit_kept(s_odo, r_odo)
    t_first, alpha, beta = cf.t_first, cf.alpha, cf.beta
    x = s_odo - t_first
    # how far the mean latency (inside alpha) lies above the link's floor: the command-time
    # offset the motion profiles reaches that far beyond its grid (Motion.shifts)
    e = r_odo[kept] - alpha - beta * x[kept]
    excess = float(-np.quantile(e, LATENCY_FLOOR_Q)) if e.size else 0.0
    if not (0.5 < beta < 1.5):
        raise DiagnoseError(f"odometer stamps and log times disagree (rate {beta:.3g}): the "
                            "bag's log times must be receive times on one clock")
    clock = {"alpha": alpha, "beta": beta, "latency_excess": excess,
             "steps": [{"when": float(at - t_first), "step": float(j)} for at, j, _ in steps],
             "rate_change": None if change is None else
             {**change, "when": change["at"] - t_first}}
    ctrl_t, ctrl_a = _control(data, cf)
    t_end = float(beta * (s_odo[-1] - t_first))
    bal_t, bal_p, bal_r, bal_id = _balises(data, line, notes, beta, t_first, t_end, train)

    v = fields["odo_speed"][idx]
    if t_end < cfg.min_duration:
        # as many digits as tell the two apart (119.95 s printed as "120.0 s ... >= 120 s")
        digits = next((d for d in range(1, 7) if round(t_end, d) < cfg.min_duration), 6)
        raise DiagnoseError(f"run too short: {t_end:.{digits}f} s of odometer data (need >= "
                            f"{cfg.min_duration:g} s)")
    if np.max(v) < cfg.min_speed:
        raise DiagnoseError(f"the train never moves (max odometer speed {np.max(v):.2f} m/s)")
    if ctrl_t.size < 2 or ctrl_t[-1] < 0.0 or ctrl_t[0] > t_end:
        raise DiagnoseError("the control commands do not overlap the odometer record")

    return Run(
        t_first=t_first, duration=t_end, odo_t=beta * x, odo_stamp=x,
        odo_d=fields["odo_distance"][idx],
        odo_v=v, odo_rv=fields["odo_speed_variance"][idx], odo_seq=unwrap(seq[idx]),
        odo_recv=r_odo, ctrl_t=ctrl_t, ctrl_a=ctrl_a, bal_t=bal_t,
        bal_p=bal_p, bal_r=bal_r, bal_id=bal_id, clock=clock, notes=notes)


def _require_topics(data: MeasuredRun) -> None:
    if _arr(data.odo_stamp).size == 0:
        raise DiagnoseError("no odometer messages in the bag: record the 'odometer' topic")
    if _arr(data.ctrl_stamp).size == 0:
        raise DiagnoseError("no control messages in the bag: diagnose replays the recorded "
                            "commands, record the 'control' topic")
    if _arr(data.balise_stamp).size == 0:
        raise DiagnoseError("no balise readings in the bag: the run cannot be placed on the "
                            "line (record the 'balise' topic)")


def unstated(var: np.ndarray, believed: float | None, what: str, notes: list) -> np.ndarray:
    """``var`` with its zeros read as *not stated* when no entry states a variance (> 0): a
    producer that leaves the field at its default (zeros mean "unknown" in ROS's covariance
    fields); ``believed`` (train.yaml's) stands in and a note says so. A stream that states
    variances elsewhere keeps its zeros, which the caller drops as corrupted."""
    var = np.asarray(var, float)
    zero = var == 0
    if believed is None or not variances_unstated(var):
        return var
    notes.append(f"{what}: every variance stated as 0 (not stated); train.yaml's "
                 f"{believed:.3g} used")
    return np.where(zero, float(believed), var)


def _odometer(data: MeasuredRun, notes: list, train=None):
    """(indices of the usable odometer readings in stamp order, the value arrays, seq)."""
    odo_s, odo_r = _arr(data.odo_stamp), _arr(data.odo_recv)
    fields = {"odo_distance": _arr(data.odo_distance), "odo_speed": _arr(data.odo_speed),
              "odo_speed_variance": unstated(
                  _arr(data.odo_speed_variance),
                  None if train is None else train.odometer_speed_variance,
                  "odometer speed_variance", notes)}
    ok = np.isfinite(odo_s) & np.isfinite(odo_r)
    for v in fields.values():
        if v.size != odo_s.size:
            raise DiagnoseError("odometer arrays differ in length")
        ok &= np.isfinite(v)
    ok &= fields["odo_speed_variance"] > 0
    if (~ok).sum():
        notes.append(f"{int((~ok).sum())} odometer readings with non-finite values or "
                     "non-positive variance dropped")
    if not ok.any():
        raise DiagnoseError(f"no usable odometer reading: all {odo_s.size} have non-finite "
                            "values or a variance <= 0")
    seq = _arr(data.odo_seq, np.int64)
    if seq.size != odo_s.size:
        seq = np.arange(odo_s.size)
    elif no_counter(seq):
        notes.append(f"every odometer seq is {int(seq[0])} (no sample counter): the link's "
                     "losses are not counted")
    idx = np.flatnonzero(ok)
    idx = idx[np.argsort(odo_s[idx], kind="stable")]
    # duplicates (same stamp) keep the first
    keep = np.concatenate([[True], np.diff(odo_s[idx]) > 0])
    if (~keep).sum():
        notes.append(f"{int((~keep).sum())} duplicate odometer stamps dropped")
    return idx[keep], fields, seq


def _control(data: MeasuredRun, cf: ClockFit):
    """Control commands in time order on the analysis axis: (t, a_tar)."""
    ctrl_s = _arr(data.ctrl_stamp)
    ctrl_a = _arr(data.ctrl_a_tar)
    if ctrl_a.size != ctrl_s.size:
        raise DiagnoseError("control arrays differ in length")
    okc = np.isfinite(ctrl_s) & np.isfinite(ctrl_a)
    order = np.argsort(ctrl_s[okc], kind="stable")
    # The motion is analysed on the reference clock (true seconds, so accelerations are not
    # scaled by a drifting train clock): odometer/balise times beta * (stamp - t_first), control
    # stamps less alpha. Times reported in parameters go back to the stamp clock (/ beta).
    ctrl_t = cf.ref_of_control(ctrl_s[okc][order])
    ctrl_a = ctrl_a[okc][order]
    keepc = np.concatenate([[True], np.diff(ctrl_t) > 0]) if ctrl_t.size else ctrl_t
    return ctrl_t[keepc], ctrl_a[keepc]


def _balises(data: MeasuredRun, line: Line, notes: list, beta: float, t_first: float,
             t_end: float, train=None):
    """Balise readings inside the odometer record: (t, position, variance, id); line.yaml's
    position wins over a reading's that contradicts it."""
    bal_s = _arr(data.balise_stamp)
    bp = _arr(data.balise_position)
    br = unstated(_arr(data.balise_variance),
                  None if train is None else train.balise_position_variance,
                  "balise position_variance", notes)
    bid = _arr(data.balise_id, np.int64)
    okb = np.isfinite(bal_s) & np.isfinite(bp) & (np.isfinite(br) & (br > 0))
    known = {b.id: b.position for b in line.balises}
    if known:
        unknown = np.array([int(i) not in known for i in bid], dtype=bool)
        # a reading of a balise the map does not list, reported off the line: its position
        # cannot be right, and taken as a fix it moved the run by kilometres (a slip of
        # 4e7 and a gradient of -45,890 per mille were fitted to absorb it)
        off = unknown & ((bp < 0.0) | (bp > line.length))
        if off.any():
            notes.append(f"{int(off.sum())} balise readings with ids not in line.yaml reported "
                         f"off the line (beyond [0, {line.length:g}] m): left out")
            okb &= ~off
            unknown &= ~off
        contra = np.array([(int(i) in known and abs(known[int(i)] - p) > 1.0)
                           for i, p in zip(bid, bp)], dtype=bool)
        if unknown.any():
            notes.append(f"{int(unknown.sum())} balise readings with ids not in line.yaml: "
                         "their reported positions are used")
        if contra.any():
            notes.append(f"{int(contra.sum())} balise readings contradict line.yaml's position: "
                         "line.yaml's is used")
            bp = np.where(contra, [known.get(int(i), p) for i, p in zip(bid, bp)], bp)
    ob = np.argsort(bal_s[okb], kind="stable")
    bal_t = beta * (bal_s[okb][ob] - t_first)
    inside = (bal_t > 0) & (bal_t < t_end)
    bal_t = bal_t[inside]
    if bal_t.size == 0:
        raise DiagnoseError("no balise reading falls inside the odometer record: the run "
                            "cannot be placed on the line")
    return bal_t, bp[okb][ob][inside], br[okb][ob][inside], bid[okb][ob][inside]

