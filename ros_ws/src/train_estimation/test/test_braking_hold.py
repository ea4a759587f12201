"""The gain of steps that do not inform f: traction 1, held at rest 0, weak trim = f estimate."""

import numpy as np

from train_estimation.core.braking.braking_model import BrakingModel, BrakingParams, discretize


def test_hold_gain_cases():
    fam = BrakingModel(BrakingParams(standstill_speed=0.3, min_brake=0.1))
    moving, still = np.array([0.0, 10.0, 0.0, 0.0]), np.array([0.0, 0.1, 0.0, 0.0])
    assert fam.hold_gain([0.5, 0.0], moving, 0.7) == 1.0
    assert fam.hold_gain([-0.5, 0.0], still, 0.7) == 0.0
    assert fam.hold_gain([-0.05, 0.0], moving, 0.7) == 0.7
    assert not fam.gate(np.array([-0.05, 0.0]), moving)  # a weak trim does not inform f
    # the shared model of a weak trim is the model of f = estimate
    Phi, Bu, _ = fam.matrices(np.array([[0.2], [0.9]]), np.array([-0.05, 0.0]), 1.0, False,
                              hold=0.7)
    Phi7, Bd7, _ = discretize(np.array([0.7]), fam.params, 1.0)
    np.testing.assert_allclose(Phi, Phi7)
    np.testing.assert_allclose(Bu, Bd7 @ np.array([-0.05, 0.0]))
