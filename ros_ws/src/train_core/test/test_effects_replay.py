"""The effects a replay of recorded commands needs beyond the true train and line
(``replay_effects``): the keywords of ``train_core.motion.replay``, from the effect dataclasses."""

import inspect

from train_core.effects import (
    AdhesionSectionEffect,
    BrakeDelayEffect,
    BrakingRateEffect,
    Effects,
    PowerLimitEffect,
    TractionDelayEffect,
    drive_effects,
    replay_effects,
)
from train_core.motion import replay


def test_no_effects_replay_the_train_as_it_is():
    assert replay_effects(Effects()) == {"brake_delay": None, "braking_rate_of_t": None,
                                         "traction_delay": None, "p_spec": None,
                                         "adhesion": None}


def test_each_effect_becomes_its_replay_keyword():
    f = BrakingRateEffect(0.9, 0.7, t_end=100.0)
    eff = Effects(braking_rate=f, brake_delay=BrakeDelayEffect(1.2),
                  traction_delay=TractionDelayEffect(0.8), power_limit=PowerLimitEffect(6.0),
                  adhesion_section=AdhesionSectionEffect(500.0, 800.0, 0.6))
    kw = replay_effects(eff)
    assert kw["brake_delay"] == 1.2 and kw["traction_delay"] == 0.8 and kw["p_spec"] == 6.0
    assert kw["adhesion"] == (500.0, 800.0, 0.6)
    assert kw["braking_rate_of_t"](50.0) == f.value(50.0)
    assert {k: kw[k] for k in ("p_spec", "adhesion")} == drive_effects(eff)
    # every keyword is one replay takes
    assert set(kw) <= set(inspect.signature(replay).parameters)
