"""`diagnose` core: what the believed model of a train gets wrong in measured data.

Work in progress (issue 10). API (stable; the CLI, tests and benchmark build on it):

    data = DiagData(...)                     # plain arrays from a bag (tools/diagnose.py)
    dg = diagnose(data, line, train, DiagConfig(), progress=None)
    dg.cause, dg.parameters, dg.ranking, dg.untestable, dg.evidence, dg.gain, dg.accepted,
    dg.series                                 # series for the plots

Pure: numpy/scipy and train_core only.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from train_core.model import Line, TrainParams

CAUSES = ("gradient", "resistance", "braking_rate", "odometer_scale", "wheel_slip",
          "bursty_link", "brake_delay", "mass", "clock_drift")


class DiagnoseError(ValueError):
    """The data cannot be diagnosed (unusable input); the message is one line saying what is
    missing or wrong and what to do."""


@dataclass(frozen=True)
class DiagData:
    """Measured series of one run, as recorded (CONTRACT.md clocks):

    odometer and balise ``*_stamp`` are on the train's clock (arbitrary epoch, may drift);
    ``control`` stamps are on the reference clock; ``*_recv`` are the bag's log (receive) times
    on the reference clock, s. Arrays in bag order (not necessarily sorted)."""

    odo_stamp: np.ndarray  # s, train clock
    odo_recv: np.ndarray  # s, reference clock (bag log time)
    odo_seq: np.ndarray  # -, uint32 sample counter before the link
    odo_distance: np.ndarray  # m
    odo_speed: np.ndarray  # m/s
    odo_speed_variance: np.ndarray  # (m/s)^2
    ctrl_stamp: np.ndarray  # s, reference clock
    ctrl_a_tar: np.ndarray  # m/s^2
    balise_stamp: np.ndarray  # s, train clock
    balise_recv: np.ndarray  # s, reference clock
    balise_id: np.ndarray  # -
    balise_position: np.ndarray  # m, surveyed position
    balise_variance: np.ndarray  # m^2


@dataclass(frozen=True)
class DiagConfig:
    max_rate: float = 5.0  # Hz, odometer samples are decimated to at most this rate
    grid_dt: float = 0.02  # s, grid of the actuator and the regressor integrals
    min_duration: float = 120.0  # s, shorter runs are refused
    min_speed: float = 1.0  # m/s, the train must exceed this somewhere
    min_brake: float = 0.05  # m/s^2, |a_Tar| above this counts as braking
    gradient_bin: float = 50.0  # m, resolution of the gradient-section search
    min_section: float = 100.0  # m, shortest gradient section considered
    penalty: str = "bic"  # complexity penalty of the score: k ln(n) (BIC)


@dataclass
class Diagnosis:
    cause: str  # first entry of ranking
    parameters: dict  # its parameters (CONTRACT.md units)
    ranking: list  # [{"cause", "score", "parameters"}], best first, "none" included
    untestable: list  # [{"cause", "why"}]
    evidence: dict  # per cause: log-likelihood gain, penalty, n, standard errors, ...
    gain: dict  # {"metric", "before", "after", ...} for the top cause
    accepted: list  # causes with score > 0 after the greedy refit, in order: [{"cause", ...}]
    series: dict = field(default_factory=dict)  # arrays for the plots


def diagnose(data: DiagData, line: Line, train: TrainParams, config: DiagConfig = DiagConfig(),
             progress: Callable[[int, int, str], None] | None = None) -> Diagnosis:
    raise NotImplementedError("diagnose core: in progress (issue 10)")
