"""The runner's clocks and door alone, on synthetic runs through the campaign's link (pure; used
by ``benchmarks/bench_clocks.py`` and the tests of the clock model's contract).

A train at constant speed sends odometer readings (with or without a sample counter) and a zone
sends commands at 1 Hz (:func:`cruise`); the readings go through ``faults.inject`` (its latency,
an exponential jitter, the train clock at a Unix epoch, a step if asked) and are replayed through
:class:`~train_estimation.core.online.runner.EstimatorRunner` with an adapter that only records
what it is given (:class:`Recorder`), so every figure of :func:`run_link` is the clocks' and the
door's, not a filter's.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from train_estimation.core.online.replay import replay
from train_estimation.core.online.runner import EstimatorRunner, Output
from train_estimation.tools import faults as F

SPEED = 20.0  # m/s, the train's constant speed
FLOOR = F.LATENCY  # s, the link's least latency (faults.LATENCY)
STEP_AT = 600.0  # s, true time of a step
WANDER_AT = 120.0  # s, true time at which a wandering latency starts to rise
COVARIANCE = tuple(np.eye(4).ravel() * 0.01)  # the Recorder's fixed estimate's covariance


class Recorder:
    """An adapter with no filter: it records the odometer readings fused (filter time s,
    counted distance m) and publishes a fixed estimate, so that the runner's clocks and door
    alone are measured."""

    def __init__(self):
        self.fused: list = []

    def snapshot(self) -> int:  # (so that the runner rewinds: a late reading, a late step)
        return len(self.fused)

    def restore(self, snap: int) -> None:
        del self.fused[snap:]

    def start(self, t0: float) -> None:
        pass

    def control(self, stamp: float, fields: dict) -> str:
        return ""

    def odometer(self, stamp: float, fields: dict) -> str:
        self.fused.append((stamp, fields.get("true_distance", fields["distance"])))
        return ""

    def balise(self, stamp: float, fields: dict) -> str:
        return ""

    def output(self, t: float) -> Output:
        return Output(t, SPEED * t, SPEED, 0.0, math.nan, COVARIANCE, True)


def cruise(duration: float, rate: float, loss: float, counter: bool,
           rng: np.random.Generator, sampling: float = 0.0, noise: tuple = (0.0, 0.0),
           speed_scale: float = 1.0, noise_corr: float = 0.0) -> list:
    """``(topic, t, fields)`` of a train at :data:`SPEED`: odometer readings at ``rate`` Hz
    (``seq`` the sample counter, or 0 for every reading without one) of which ``loss`` are lost
    at random, and a command every second. ``sampling``: s, the sampling loop's own jitter:
    each sample is taken (and stamped) a Gaussian of this spread off its slot. ``noise``: (m,
    m/s), the standard deviations of the count's and the speed's Gaussian noise per reading
    (the true count rides along as ``true_distance``, for the time errors). ``speed_scale``: the
    speed field's scale against the count's rate (a speed from another sensor: a radar, a
    second axle). ``noise_corr``: the count's noise's correlation from one reading to the next
    (an AR(1) of the same spread: a count smoothed by its producer)."""
    ev = []
    n = int(round(duration * rate))
    kept = np.flatnonzero(rng.random(n) >= loss)
    late = rng.normal(0.0, sampling, kept.size) if sampling else np.zeros(kept.size)
    sd_d, sd_v = noise
    e_d = rng.normal(0.0, sd_d, kept.size) if sd_d else np.zeros(kept.size)
    if noise_corr:  # an AR(1) of the same spread
        for i in range(1, kept.size):
            e_d[i] = noise_corr * e_d[i - 1] + math.sqrt(1.0 - noise_corr ** 2) * e_d[i]
    e_v = rng.normal(0.0, sd_v, kept.size) if sd_v else np.zeros(kept.size)
    for k, dt, ed, ev_ in zip(kept, late, e_d, e_v):
        t = k / rate + float(dt)
        f = {"seq": int(k) if counter else 0, "distance": SPEED * t + float(ed),
             "speed": SPEED * speed_scale + float(ev_), "speed_variance": max(sd_v, 0.1) ** 2}
        if sd_d:
            f["true_distance"] = SPEED * t
        ev.append(("odometer", t, f))
    ev += [("control", float(j), {"target_acceleration": 0.0})
           for j in range(int(duration) + 1)]
    return sorted(ev, key=lambda e: (e[1], e[0] != "control"))


def _later(faulted, extra):
    """The stream with each odometer and balise reading arriving ``extra(fields)`` s later
    (called for them in stream order), in arrival order again."""
    ev = [(tp, st, f, ar + (extra(f) if tp in F.TRAIN_TOPICS else 0.0))
          for tp, st, f, ar in faulted.events]
    return replace(faulted, events=sorted(ev, key=lambda e: e[3]))


def run_link(duration: float, rate: float, counter: bool, jitter: float, loss: float,
             step: float | None, seed: int, queue: float | None = None,
             route: float | None = None, shape: str = "exp", drift: float = 0.0,
             sampling: float = 0.0, wander: tuple | None = None,
             count_clock: bool = True, noise: tuple = (0.0, 0.0),
             speed_scale: float = 1.0, noise_corr: float = 0.0, count_jump: float = 0.0) -> dict:
    """One replay (module doc); the figures of one row. ``queue``: the drain factor of a link
    that queues (the campaign's fault ``queue``, from 15 s on; no step then); ``route``: s by
    which the link's latency rises at :data:`STEP_AT` and stays (the fault ``route``; no
    step then); ``shape``: the jitter's law, ``exp`` (the campaign's, exponential of mean
    ``jitter``) or ``gamma`` (Gamma of shape 4 and the same mean: a latency that seldom comes
    near its floor, so that the offsets' envelope is blunt); ``drift``: s/s, the train clock runs
    at ``1 + drift`` against the commands' and the arrivals' clock (the fault ``drift``; no step
    then); ``sampling``: s, the sampling loop's jitter on the stamps (:func:`cruise`);
    ``wander``: (rise s, period s), the link's latency rises by ``rise`` from
    :data:`WANDER_AT` and falls back over ``period`` (a raised cosine), a link that slows down
    for a while (no step then); ``count_clock``: the runner's (False: a stream without a
    counter judged by its arrivals alone, as when the train is slow); ``noise``: the count's
    and the speed's noise (m, m/s; :func:`cruise`); ``speed_scale``: the speed field's scale
    against the count, and ``noise_corr`` its noise's correlation (:func:`cruise`);
    ``count_jump``: m added to every count sampled from :data:`STEP_AT` on (a producer that
    re-bases its count; the stamps stay)."""
    rng = np.random.default_rng(seed)
    events = cruise(duration, rate, loss, counter, rng, sampling, noise, speed_scale, noise_corr)
    if count_jump:
        for ev in events:
            f = ev[2]
            if ev[0] == "odometer" and ev[1] >= STEP_AT - 1e-9:
                f["true_distance"] = f.get("true_distance", f["distance"])
                f["distance"] += count_jump
    if shape not in ("exp", "gamma"):
        raise ValueError(f"shape must be exp or gamma, got {shape!r}")
    link = jitter if shape == "exp" else 0.0
    fault = F.Fault("none", jitter=link) if step is None else \
        F.Fault("step", step, STEP_AT, jitter=link)
    if queue is not None:
        fault = F.Fault("queue", queue, 0.5 * F.QUEUE_EVERY, jitter=link)
    if route is not None:
        fault = F.Fault("route", route, STEP_AT, jitter=link)
    if drift:
        fault = F.Fault("drift", drift, 0.0, jitter=link)
    faulted = F.inject(events, fault, rng)
    if shape == "gamma":
        faulted = _later(faulted, lambda f: rng.gamma(4.0, jitter / 4.0))
    if wander is not None:
        rise, period = wander

        def wandered(f):
            # s since the rise began (the sample's time)
            u = f.get("true_distance", f["distance"]) / SPEED - WANDER_AT
            return 0.5 * rise * (1.0 - math.cos(2.0 * math.pi * u / period)) \
                if 0.0 <= u <= period else 0.0

        faulted = _later(faulted, wandered)
    rec = Recorder()
    runner = EstimatorRunner(rec, 1.0 / rate, count_clock=count_clock)
    arrived = {"new": 0}  # readings sampled at or after the step's instant, arrived so far
    decided = []  # (true arrival s, new readings arrived) when the step was declared

    def on_time(t_arr: float) -> None:
        if not decided and runner.events.get("odometer:clock_reset"):
            decided.append((t_arr - F.EPOCH, arrived["new"]))

    def stream():
        for ev in faulted.events:
            yield ev
            if ev[0] == "odometer" and \
                    ev[2].get("true_distance", ev[2]["distance"]) / SPEED >= STEP_AT - 1e-9:
                arrived["new"] += 1

    outs, _ = replay(stream(), rec, 1.0 / rate, on_time=on_time, runner=runner)
    hours = duration / 3600.0
    # in doubt while readings are held as a possible step (or just re-anchored), and apart,
    # while a declared step may still be a burst of wrong stamps (its prior, not the data)
    burst = sum("may be a burst" in o.integrity_reason for o in outs)
    doubted = sum("clock" in o.integrity_reason for o in outs) - burst
    row = {"false_steps_per_h": runner.events.get("odometer:clock_reset", 0) / hours
           if step is None else math.nan,
           "refused": sum(runner.rejected.values()),
           "held": doubted / max(len(outs), 1), "doubted": doubted, "burst": burst,
           "latency_moved": runner.events.get("odometer:link_latency", 0),
           "count_slips": runner.events.get("odometer:count_slip", 0)}
    # where the clock is with the least latency: stamp - arrival = -FLOOR on this link
    train = runner._offsets.get("train")
    row["bias_ms"] = 1e3 * (train.value + FLOOR) if train is not None else math.nan
    # one clock (the commands' and the readings' share the epoch and the rate): judged so?
    row["separate"] = runner.separate_clocks
    row["drift_ppm"], row["drift_se_ppm"] = (1e6 * v for v in train.rate()) \
        if train is not None else (math.nan, math.nan)
    # the filter time of each reading fused against its true sampling time, relative to the
    # first (the filter's time origin is its own); with a step, from the last one before it
    f = np.array(rec.fused, float).reshape(-1, 2)
    t_true = f[:, 1] / SPEED  # the train cruises: its count is its sampling time
    e = f[:, 0] - t_true
    row["time_err_all_ms"] = 1e3 * float(np.max(np.abs(e - e[0]))) if e.size else math.nan
    if step is not None:
        row["shift_err_ms"] = 1e3 * (runner._steps.shift - step)
        t_dec, n_new = decided[0] if decided else (math.nan, math.nan)
        row["decided_readings"], row["decided_s"] = n_new, t_dec - STEP_AT
        before, after = t_true < STEP_AT, t_true >= STEP_AT
        row["time_err_ms"] = 1e3 * float(np.max(np.abs(e[after] - e[before][-1]))) \
            if after.any() and before.any() else math.nan
    return row
