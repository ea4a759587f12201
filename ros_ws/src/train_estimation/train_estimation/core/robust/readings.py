"""Message-shaped inputs and outputs of the filters: the readings a node builds from its
messages, the decision it gets back, and the ``TrainState.covariance`` layout.

The filters (``filter_base``) validate the readings and turn them into measurement channels;
see there for what each reading means to the filter.

Pure: numpy only.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .. import reasons as R

__all__ = ["Decision", "OdometerReading", "BaliseReading", "REASONS", "covariance16"]

# the filters' share of the one vocabulary (core/reasons.py)
REASONS = (R.OK, R.MISSING, R.IGNORED,  # accepted
           R.NON_FINITE, R.NON_POSITIVE_VARIANCE, R.OUT_OF_ORDER, R.DUPLICATE,  # rejected
           R.UNKNOWN_BALISE, R.BALISE_MAP_MISMATCH, R.OUTSIDE_GATE)



@dataclass(frozen=True)
class Decision:
    accepted: bool
    reason: str  # one of REASONS


@dataclass(frozen=True)
class OdometerReading:
    stamp: float  # s, sampling time on the train
    seq: int  # sample counter before the radio link
    distance: float = math.nan  # m, counted since the run started
    speed: float = math.nan  # m/s
    speed_variance: float = math.nan  # (m/s)^2
    received: bool = True  # False: the slot of sample ``seq`` was lost (values ignored)


@dataclass(frozen=True)
class BaliseReading:
    stamp: float  # s, time the antenna passed the reference mark
    seq: int
    balise_id: int
    position: float  # m, surveyed position as sent
    position_variance: float  # m^2
    # m, where the train stood at ``stamp`` by this reading when that is not the map position
    # itself (the calibration's reader latency moves it by the speed times the latency); None:
    # the map position. ``position`` is still checked against the map (the message as sent).
    measured: float | None = None


def covariance16(Sigma: np.ndarray) -> list[float]:
    """``TrainState.covariance``: row-major 4x4 over (position, velocity, acceleration,
    braking_rate) with the 2x2 ``Sigma`` in the top-left corner and NaN elsewhere."""
    out = np.full((4, 4), np.nan)
    out[:2, :2] = Sigma
    return [float(v) for v in out.ravel()]
