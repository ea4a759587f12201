"""`diagnose` core: what the believed model of a train gets wrong in measured data.

Given one run (``core.offline.measured.MeasuredRun``: odometer, balise and control series with the
bag's log times) and the railway's believed ``line.yaml``/``train.yaml``, find which of
docs/interfaces.md's causes explains the data, fit it, and rank every cause.

- ``run``: the measured run and its preparation (order, clean, the clock fit);
- ``motion``: the motion model, its time grid, the reference trajectory placed on the line by
  the balises, and the elementary columns every cause is built from;
- ``stage``: the null, its noise fit, the augmented Kalman filter and the GLS of any set of
  columns against it;
- ``causes``: one module per cause and the registry;
- ``search``: greedy stages, prior odds, the refit at a cause's own noise; ``refit``: the joint
  refit of the accepted causes and Occam's steps (merge, unlocate);
- ``confirm``: the checks that confirm an accepted cause (``contradict``: where it shows and
  only there; ``laws``: rival laws of its effect; ``halves``: a sensor cause's halves of the
  run, and a place cause's halves of its stretch, agree);
  ``verdict``: the confirmation, what the model leaves, the ranking and the evidence;
- ``gain``: held-out gains;
- ``result``: :class:`CauseFit`, :class:`Diagnosis` and their JSON.

Pure: numpy/scipy and train_core only.
"""

from .causes import BY_NAME, CAUSES, REGISTRY, ModelContext
from .causes.bursty_link import gilbert_elliott_vs_bernoulli, link_test
from .causes.clock_drift import clock_test
from .motion import Motion, place_on_line
from .refit import joint_refit
from .result import REPORT_KEYS, CauseFit, Diagnosis, jsonable
from .run import DiagConfig, DiagnoseError, Run, prepare
from .search import diagnose
from .stage import Null, Stage, best_section

__all__ = ["BY_NAME", "CAUSES", "REGISTRY", "REPORT_KEYS", "CauseFit", "DiagConfig",
           "DiagnoseError", "Diagnosis", "ModelContext", "Motion", "Null", "Run", "Stage",
           "best_section", "clock_test", "diagnose", "joint_refit", "jsonable", "link_test",
           "gilbert_elliott_vs_bernoulli", "place_on_line", "prepare"]
