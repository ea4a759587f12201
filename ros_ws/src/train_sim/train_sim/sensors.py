"""On-board sensors: axle odometer and balise reader (before the radio link).

Odometer (sampled at ``odometer_rate``, default 10 Hz)::

    distance_k = D_axle(t_k) + e_d,   e_d ~ N(0, distance_std^2)   (independent per sample)
    speed_k    = v_axle(t_k) + e_v,   e_v ~ N(0, speed_std^2)
    speed_variance_k = speed_std^2    (the sensor's stated variance, from train.yaml)

where v_axle = scale * slip(t) * v is the speed the axle rotation shows and D_axle its integral
from the start of the run (both equal the truth without the odometer_scale / wheel_slip effects).
The noise is Gaussian at standstill too (no clipping), so the stated variance is the true one.

Balises: the antenna detects balise i when the train's reference end passes
``position_i + e_i``, e_i ~ N(0, balise_position_std^2) drawn once per balise (detection/timing
error); the reading reports the *surveyed* position from the line map with variance
balise_position_std^2. The detection instant is interpolated linearly inside the integration
step (<= 10 ms), far finer than the metre-level error.

``seq`` counts samples before the radio link (+1 per sample, from 0), so gaps in received seq
reveal dropouts. Randomness only through the generators passed in.

Pure module: numpy only.
"""

from __future__ import annotations

from bisect import bisect_right

import numpy as np
from train_core.model import Balise


class Odometer:
    """Adds the sensor noise and the sequence counter to the axle's distance and speed."""

    def __init__(self, speed_std: float, distance_std: float, rng: np.random.Generator,
                 block: int = 1024):
        self.speed_std = float(speed_std)
        self.distance_std = float(distance_std)
        self.speed_variance = self.speed_std**2
        self.rng = rng
        self.seq = 0
        self._block = block
        self._buf = np.empty((0, 2))
        self._i = 0

    def _noise(self) -> tuple[float, float]:
        # Standard normals drawn in fixed-size blocks: sample k's noise depends only on the
        # generator's seed and k, never on how many samples a run takes.
        if self._i >= len(self._buf):
            self._buf = self.rng.standard_normal((self._block, 2))
            self._i = 0
        z = self._buf[self._i]
        self._i += 1
        return float(z[0]), float(z[1])

    def sample(self, axle_distance: float, axle_speed: float) -> tuple[int, float, float, float]:
        """(seq, distance m, speed m/s, speed_variance (m/s)^2) of one sample."""
        zd, zv = self._noise()
        seq = self.seq
        self.seq += 1
        return (seq, axle_distance + self.distance_std * zd, axle_speed + self.speed_std * zv,
                self.speed_variance)


class BaliseReader:
    """Detects balise passages along a forward-moving trajectory."""

    def __init__(self, balises: tuple[Balise, ...], position_std: float,
                 rng: np.random.Generator, start_position: float, moved: dict | None = None):
        """``moved``: balise id -> m it lies from the position it reports (a test effect,
        train_sim.unlisted.MisplacedBalise)."""
        moved = moved or {}
        ordered = sorted(balises, key=lambda b: b.position)
        offsets = rng.standard_normal(len(ordered)) * position_std  # one per balise, line order
        pairs = sorted(zip((b.position + moved.get(b.id, 0.0) + float(e)
                            for b, e in zip(ordered, offsets)), ordered),
                       key=lambda p: p[0])
        self.triggers = [p[0] for p in pairs]  # m, true positions where each balise is read
        self.balises = [p[1] for p in pairs]
        self.position_variance = float(position_std) ** 2
        self.seq = 0
        # Only balises strictly ahead of the start can be passed.
        self._next = bisect_right(self.triggers, start_position)

    @property
    def next_trigger(self) -> float:
        return self.triggers[self._next] if self._next < len(self.triggers) else float("inf")

    def crossings(self, t0: float, x0: float, t1: float, x1: float) -> list[tuple[float, Balise]]:
        """Balises passed in (x0, x1] during [t0, t1], with linearly interpolated times."""
        out = []
        trig = self.triggers
        while self._next < len(trig) and trig[self._next] <= x1:
            xt = trig[self._next]
            frac = (xt - x0) / (x1 - x0) if x1 > x0 else 1.0
            out.append((t0 + frac * (t1 - t0), self.balises[self._next]))
            self._next += 1
        return out

    def reading(self, balise: Balise) -> tuple[int, int, float, float]:
        """(seq, balise_id, surveyed position m, position_variance m^2)."""
        seq = self.seq
        self.seq += 1
        return seq, balise.id, float(balise.position), self.position_variance
