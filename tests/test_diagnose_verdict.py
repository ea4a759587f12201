"""The noise at which diagnose's verdict tests what the confirmed model leaves
(diagnose/verdict.py ``verdict_noise``): accepted causes the data contradicted are left out, as
if the search had not accepted them; the others, confirmed or not, stay."""

from __future__ import annotations

from types import SimpleNamespace

from train_estimation.core.offline.diagnose import verdict
from train_estimation.core.offline.diagnose.result import CauseFit

STAGES = [{"q": 1e-2, "r_s": 0.05}, {"q": 2e-4, "r_s": 0.051}, {"q": 3e-5, "r_s": 0.052}]
FULL = (1e-5, 0.053)  # the noise of the model with every accepted cause


def _fit(cause, stage, status, why=None):
    return CauseFit(cause, 10.0, {}, stage=stage, status=status, why=why)


def _search(accepted, merged=()):
    return SimpleNamespace(accepted=accepted, merged=list(merged), stages=STAGES, mo=None,
                           cfg=None)


def test_a_cause_without_evidence_or_of_an_implausible_size_keeps_its_noise():
    sr = _search([_fit("gradient", 1, "not confirmed", "not a map error: +46 per mille"),
                  _fit("mass", 2, "not confirmed", "held-out check failed: Z 1.2"),
                  _fit("resistance", 3, "confirmed")])
    assert verdict.verdict_noise(sr, 0.0, FULL) == (FULL, [])


def test_a_contradicted_cause_accepted_last_gives_the_noise_of_the_stage_that_accepted_it():
    for why in ("contradicted by the phase split: the fitted effect is needed x-6.5",
                "not a slip: the odometer's speed readings step by less than half"):
        sr = _search([_fit("gradient", 1, "not confirmed", "not a map error: +46 per mille"),
                      _fit("wheel_slip", 2, "not confirmed", why)])
        assert verdict.verdict_noise(sr, 0.0, FULL) == ((2e-4, 0.051), ["wheel_slip"])


def test_a_contradicted_cause_before_a_kept_one_is_left_out_of_a_noise_fitted_again(
        monkeypatch):
    """No stage held the model without it: the noise is fitted on the kept causes (and so
    after a merge, which replaced what the stages held)."""
    seen = []

    def null_of(mo, shift, fits):
        seen.append([f.cause for f in fits])
        return "null"

    class Stage:
        def __init__(self, mo, null, cfg, big=True):
            assert null == "null" and not big
            self.q, self.r_s = 7e-5, 0.06

    monkeypatch.setattr(verdict, "_null_of", null_of)
    monkeypatch.setattr(verdict, "Stage", Stage)
    slip = _fit("wheel_slip", 1, "not confirmed", "contradicted by the phase split: x-3")
    grad = _fit("gradient", 2, "confirmed")
    assert verdict.verdict_noise(_search([slip, grad]), 0.0, FULL) == ((7e-5, 0.06),
                                                                       ["wheel_slip"])
    assert seen == [["gradient"]]
    grad1 = _fit("gradient", 1, "confirmed")
    slip2 = _fit("wheel_slip", 2, "not confirmed", "contradicted by the phase split: x-3")
    merged = _search([grad1, slip2], merged=[_fit("resistance", 1, "not confirmed")])
    assert verdict.verdict_noise(merged, 0.0, FULL) == ((7e-5, 0.06), ["wheel_slip"])
    assert seen[-1] == ["gradient"]


def test_a_balise_latency_entry_says_which_way_the_streams_are_off():
    """The latency test's tau > 0: the balises lie behind the odometer's position, the reader
    stamps late. tau < 0: they lie ahead of it, and either the reader stamps early or the
    odometer's readings are older than their stamps (a whole odometer message 0.3 s old was
    reported as a reader that stamps late). Both are told as a balise latency by the tool."""
    from train_estimation.tools.diagnose_unexplained import balise_latency, unexplained_line

    entries = {tau: verdict._entry({"family": "balise_latency", "speed": [5.0, 30.0],
                                    "size": tau}, []) for tau in (0.3, -0.3)}
    late, early = (entries[t]["best_listed"]["why"] for t in (0.3, -0.3))
    assert "+0.300 s x speed; behind it): the balise reader stamps them late" in late
    assert "-0.300 s x speed; ahead of it)" in early and "stamps them late" not in early
    assert "odometer's readings are older than their stamps" in early
    assert all(balise_latency(e) for e in entries.values())
    line = {t: unexplained_line(dict(e, where=None, when=None)) for t, e in entries.items()}
    assert "0.300 s x speed behind" in line[0.3] and "reader stamps late" in line[0.3]
    assert "0.300 s x speed ahead of" in line[-0.3] and "stamps late" not in line[-0.3]
