"""train_core.effects writes what it parses: effects_to_dict -> parse_effects is the identity."""

import pytest
import yaml
from train_core.config import ConfigError, Section
from train_core.effects import (
    EFFECT_NAMES,
    AdhesionSectionEffect,
    BrakeDelayEffect,
    BrakingRateEffect,
    BurstyLinkEffect,
    ClockDriftEffect,
    Effects,
    GradientEffect,
    MassEffect,
    OdometerScaleEffect,
    PowerLimitEffect,
    ResistanceEffect,
    TractionDelayEffect,
    WheelSlipEffect,
    effect_to_dict,
    effects_to_dict,
    parse_effects,
)

DURATION = 600.0

EVERY = Effects(
    gradient=GradientEffect(2400.0, 2800.0, 4.25),
    resistance=ResistanceEffect(4000.0, 160.0, 9.5),
    braking_rate=BrakingRateEffect(0.95, 0.85, t_start=10.0, t_end=500.0),
    odometer_scale=OdometerScaleEffect(1.01),
    wheel_slip=WheelSlipEffect(((50.0, 52.0), (120.0, 122.5)), slip_fraction=0.12),
    bursty_link=BurstyLinkEffect(0.03, 0.2, loss_good=0.01, loss_bad=0.9),
    brake_delay=BrakeDelayEffect(1.6),
    mass=MassEffect(310000.0),
    clock_drift=ClockDriftEffect(0.001),
    power_limit=PowerLimitEffect(9.5),
    adhesion_section=AdhesionSectionEffect(3100.0, 3400.0, 0.7),
    traction_delay=TractionDelayEffect(1.5),
)


def _parse(d: dict) -> Effects:
    # through YAML text, as a scenario's effects.yaml is read
    return parse_effects(Section(yaml.safe_load(yaml.safe_dump(d)), "effects.yaml"), DURATION)


def test_every_effect_round_trips():
    assert set(EVERY.active()) == set(EFFECT_NAMES)
    assert _parse(effects_to_dict(EVERY)) == EVERY


@pytest.mark.parametrize("eff", [
    Effects(braking_rate=BrakingRateEffect(1.0, 0.9, mode="step", t_end=DURATION, t_step=42.0)),
    Effects(braking_rate=BrakingRateEffect(1.0, 0.9, t_end=DURATION)),
    Effects(wheel_slip=WheelSlipEffect(((1.0, 2.0),))),
    Effects(bursty_link=BurstyLinkEffect(0.1, 0.5)),
    Effects(),
])
def test_defaults_are_left_out_and_come_back(eff):
    d = effects_to_dict(eff)
    assert _parse(d) == eff
    for name, params in d.items():
        default_fields = {"mode": "linear", "t_start": 0.0, "loss_good": 0.0, "loss_bad": 1.0}
        for k, v in default_fields.items():
            if k in params:
                assert params[k] != v, (name, k)


def test_written_values_are_plain_yaml_types():
    d = effect_to_dict(EVERY.wheel_slip)
    assert d == {"intervals": [[50.0, 52.0], [120.0, 122.5]], "slip_fraction": 0.12}
    assert yaml.safe_load(yaml.safe_dump(effects_to_dict(EVERY))) == effects_to_dict(EVERY)


def test_the_parser_still_refuses_what_it_refused():
    bad = effects_to_dict(Effects(gradient=GradientEffect(100.0, 200.0, 90.0)))
    with pytest.raises(ConfigError):
        _parse(bad)
