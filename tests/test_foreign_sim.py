"""The independent simulator of benchmarks/bench_foreign.py: its own physics, contract bags."""

import ast
import os
import sys

import numpy as np
import pytest

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, "..", "benchmarks"))
import foreign_sim as FS  # noqa: E402

LINE = {"length": 3000.0, "max_speed": 20.0,
        "balises": [{"id": i + 1, "position": p} for i, p in enumerate((50.0, 1500.0, 2950.0))],
        "gradients": [{"start": 0.0, "end": 3000.0, "permille": 0.0}],
        "stations": [{"name": "A", "position": 100.0}, {"name": "B", "position": 2900.0}]}
TRAIN = {"mass": 300000.0, "rotary_allowance": 0.1, "davis": {"a": 3000.0, "b": 100.0, "c": 8.0},
         "brake": {"time_constant": 0.5, "delay": 1.0, "braking_rate": 1.0},
         "performance": {"max_traction": 0.8, "service_brake": 0.8}}


@pytest.fixture(autouse=True)
def _pilots_shared():
    """bench_foreign draws each seed's line and train with train_sim.cases.make_case, whose
    pilot run of the same case these tests repeat: run once per worker
    (conftest.simulations_shared, a bit-identical copy each time)."""
    from conftest import simulations_shared

    with simulations_shared():
        yield


def test_it_shares_no_physics_with_ours():
    src = open(FS.__file__).read()
    mods = {n.module or "" for n in ast.walk(ast.parse(src)) if isinstance(n, ast.ImportFrom)}
    mods |= {a.name for n in ast.walk(ast.parse(src)) if isinstance(n, ast.Import)
             for a in n.names}
    assert not any(m.startswith("train_sim") for m in mods), mods
    assert {m for m in mods if m.startswith("train_core")} <= {"train_core.bagio"}, mods


@pytest.mark.parametrize("effect", [FS.Effect(), FS.Effect(gradient=(1000.0, 1400.0, 5.0),
                                                           clock_drift=1e-4)])
def test_a_run_from_station_to_station_keeps_the_contract(effect):
    tr, sent, truth = [], [], []
    ev = FS.simulate(LINE, TRAIN, effect, np.random.default_rng(0), trace=tr, sent=sent,
                     truth=truth)
    # the clean stream: every message logged, at its true sample time; the truth per sample
    assert len(sent) == len(ev)
    assert [e[0] for e in sent].count("odometer") == [e[1] for e in ev].count("odometer")
    assert np.all(np.diff([u[0] for u in truth]) > 0) and truth[-1][1] == pytest.approx(
        tr[-1][1], abs=30.0)
    x = np.array([r[1] for r in tr])
    assert x[-1] > 2850.0  # it reached the last station (a few metres either side)
    log = [e[0] for e in ev]
    assert log == sorted(log)
    odo = sorted((e for e in ev if e[1] == "odometer"), key=lambda e: e[3]["seq"])
    seq = np.array([e[3]["seq"] for e in odo])
    st = np.array([e[2] for e in odo])
    assert np.all(np.diff(seq) > 0) and np.all(np.diff(st) > 0)
    # the train clock's rate against the sample counter: 10 Hz times (1 + drift)
    rate = np.polyfit(seq, st, 1)[0] * 10.0 - 1.0
    assert rate == pytest.approx(effect.clock_drift, abs=1e-7)
    # losses happen, and the counted distance ends near the distance run
    assert 0 < seq.size < seq[-1] + 1
    assert odo[-1][3]["distance"] == pytest.approx(x[-1] - x[0], abs=2.0)
    bal = [e for e in ev if e[1] == "balise"]
    assert {e[3]["balise_id"] for e in bal} <= {1, 2, 3}


@pytest.mark.slow
def test_a_downhill_run_in_braking_is_named_with_the_rival_it_cannot_be_told_from(tmp_path):
    """A downhill section the map lacks, run wholly in a braking approach at a nearly constant
    braking command (bench_foreign's gradient at seed 1): the same force as braking weaker on
    that stretch. It was confirmed as a low-adhesion section with the fixed force 1.4 ahead;
    one run cannot tell the two apart (docs/diagnose.md, check 3: the braking law), so neither
    is confirmed: the section's entry names the rival and what would tell, and its effect is
    reported as left, on the stretch."""
    import json

    import bench_foreign as BF

    from train_estimation.tools import diagnose as tool

    seed = 1
    _, paths, line, train, pilot, eff = BF.foreign_case(seed, "gradient",
                                                        str(tmp_path / "case"))
    s0, s1, pm = eff.gradient
    x, _, cmd, _ = pilot
    on = (x >= s0) & (x < s1)
    assert pm < 0 and np.all(cmd[on] < 0)  # downhill, wholly in braking
    FS.write_bag(FS.simulate(line, train, eff, np.random.default_rng([seed, 3])),
                 str(tmp_path / "bag"))
    assert tool.main(["--bag", str(tmp_path / "bag"), "--line", str(paths["line"]), "--train",
                      str(paths["train"]), "--out", str(tmp_path / "out"), "--quiet"]) == 0
    rep = json.loads((tmp_path / "out" / "report.json").read_text())
    assert rep["cause"] == "unexplained", rep["cause"]
    assert not [r for r in rep["ranking"] if r["status"] == "confirmed"], rep["ranking"][:2]
    sec = next(r for r in rep["ranking"] if r["cause"] == "adhesion_section")
    assert sec["status"] == "not confirmed", sec
    assert sec["why"].startswith("one run cannot tell it from"), sec
    assert "downhill gradient" in sec["why"] and "braked differently" in sec["why"], sec
    lr = rep["evidence"]["_model"]["confirmation"]["checks"]["adhesion_section"][
        "braking_law"]["lr"]
    assert abs(lr) <= 9.0, lr
    u = rep["unexplained"][0]
    assert u["phase"] == "braking" and u["best_listed"]["cause"] == "adhesion_section", u
    overlap = min(u["where"][1], s1) - max(u["where"][0], s0)
    assert overlap > 0.8 * (s1 - s0), (u, eff.gradient)
    # the gradient's 4.15 per mille is 0.041 m/s^2 less braking there
    assert abs(u["size"] + 9.81 * pm / 1000.0) < 0.015, (u, pm)
    # printed as what it is, not as the odometer's count (an entry with a stretch and a span)
    from train_estimation.tools.diagnose_unexplained import unexplained_line

    line_ = unexplained_line(u)
    assert "one run cannot tell" in line_ and "odometer counts" not in line_, line_


def test_a_warming_resistance_leaves_no_section_on_its_braking_stretch(tmp_path):
    """A resistance decaying from the start (bench_foreign --unlisted warmup, seed 2) draws a
    gradient, a resistance and a low-adhesion section braked over at one command. The
    gradient is not one size over its stretch (its halves 7.0 and 5.7 per mille, z +3.6), the
    resistance does no better than a free acceleration per phase beside the section, and the
    section is contradicted by its split (needed about -1.8 times itself in braking at every
    speed): it is not reported as a braking effect on its stretch, and the remainder's first
    entry is in every phase, as a warm-up acts. (Before the place causes' halves test, the
    section was contradicted only once judged again without the two others: held out at Z
    -0.46.) With each fold's fit on the filter of every reading, the section fails its held-out
    check first (a held-out gain below 0): either way it is not confirmed."""
    rep, _ = _diagnose_foreign(tmp_path, 2, "warmup")
    assert rep["cause"] == "unexplained", rep["cause"]
    st = {r["cause"]: r for r in rep["ranking"]}
    assert st["gradient"]["why"].startswith("the data's halves fit it differently"), \
        st["gradient"]
    sec = st["adhesion_section"]
    assert sec["status"] == "not confirmed" and \
        sec["why"].startswith(("contradicted by the phase split", "held-out check failed")), sec
    assert rep["unexplained"][0]["phase"] == "all", rep["unexplained"]
    assert not [u for u in rep["unexplained"]
                if (u.get("best_listed") or {}).get("cause") == "adhesion_section"]


def test_a_coasting_driver_coasts_and_still_stops_at_the_last_station():
    """Coast-and-motor driving (bench_foreign --coast): from its cruise speed (0.9 x 20 m/s
    here) the driver coasts, motoring again only below the given fraction of it; the default
    holds the cruise speed (its zero commands are those of a small speed error)."""
    runs = {}
    for coast in (0.0, 0.8):
        tr: list = []
        FS.simulate(LINE, TRAIN, FS.Effect(), np.random.default_rng(0), trace=tr, coast=coast)
        t, x, v, cmd = (np.array([r[i] for r in tr]) for i in range(4))
        moving = v[:-1] > 1.0
        coasting = moving & (cmd[:-1] == 0.0)
        fast = v[:-1][coasting & (v[:-1] > 10.0)]
        runs[coast] = (np.sum(np.diff(t)[coasting]) / np.sum(np.diff(t)[moving]), x[-1],
                       fast.min(), fast.max())
    share0, _, lo0, hi0 = runs[0.0]
    share, end, lo, hi = runs[0.8]
    assert abs(lo0 - 18.0) < 0.2 and abs(hi0 - 18.0) < 0.2, runs
    assert share > share0 + 0.2 and 0.8 * 18.0 - 0.2 < lo < 17.0 and hi < 18.2, runs
    assert end > 2850.0  # it reached the last station


def _diagnose_foreign(tmp_path, seed: int, kind: str, family: str | None = None,
                      **sim_kw) -> tuple:
    import json

    import bench_foreign as BF

    from train_estimation.tools import diagnose as tool

    _, paths, line, train, _, eff = BF.foreign_case(seed, kind, str(tmp_path / "case"), family,
                                                    sim_kw)
    FS.write_bag(FS.simulate(line, train, eff, np.random.default_rng([seed, 3]), **sim_kw),
                 str(tmp_path / "bag"))
    assert tool.main(["--bag", str(tmp_path / "bag"), "--line", str(paths["line"]), "--train",
                      str(paths["train"]), "--out", str(tmp_path / "out"), "--quiet"]) == 0
    return json.loads((tmp_path / "out" / "report.json").read_text()), eff


def test_effects_outside_the_list_change_what_they_say_and_nothing_else():
    rng = [np.random.default_rng(3) for _ in range(2)]
    nominal = FS.simulate(LINE, TRAIN, FS.Effect(), rng[0])
    for eff, topic, field in (
            (FS.Effect(odometer_bias=0.1), "odometer", "speed"),
            (FS.Effect(odometer_lag=0.3), "odometer", "speed"),
            (FS.Effect(balise_moved=(2, 15.0)), "balise", None),
            (FS.Effect(brake_fade=(5.0, 0.6)), "odometer", "distance"),
            (FS.Effect(wind=(30.0, 90.0, 20000.0)), "odometer", "distance"),
            (FS.Effect(clock_step=(60.0, 2.0)), "odometer", "stamp")):
        ev = FS.simulate(LINE, TRAIN, eff, np.random.default_rng(3))
        # the same messages before the effect could act (same driver, link and noise draws)
        assert [e[1] for e in ev[:20]] == [e[1] for e in nominal[:20]]
        a = [e for e in nominal if e[1] == topic]
        b = [e for e in ev if e[1] == topic]
        if field == "stamp":
            assert max(abs(x[2] - y[2]) for x, y in zip(a, b)) == pytest.approx(2.0, abs=1e-6)
        elif field is None:  # the moved balise is read later, with its map position
            ta = {x[3]["balise_id"]: x[2] for x in a}
            tb = {x[3]["balise_id"]: (x[2], x[3]["position"]) for x in b}
            assert tb[2][0] > ta[2] + 0.5 and tb[2][1] == 1500.0
        else:
            assert max(abs(x[3][field] - y[3][field]) for x, y in zip(a, b)) > 0.05
        if eff.odometer_lag:  # the speed lags, the count does not
            assert all(x[3]["distance"] == y[3]["distance"] for x, y in zip(a, b))


def test_an_effect_outside_the_list_on_foreign_data_is_unexplained_in_its_phase(tmp_path):
    """Braking that fades below a speed, from the foreign simulator (bench_foreign --unlisted,
    seed 0): no listed cause is confirmed, the remainder is named in braking."""
    rep, eff = _diagnose_foreign(tmp_path, 0, "brake_fade")
    assert eff.brake_fade is not None
    assert rep["cause"] == "unexplained", rep["cause"]
    assert not [r for r in rep["ranking"] if r.get("status") == "confirmed"]
    assert rep["unexplained"][0]["phase"] == "braking", rep["unexplained"][0]


@pytest.mark.parametrize("seed,listed", [(1, "braking_rate"), (3, "adhesion_section"),
                                         (5, "braking_rate")])
def test_brakes_that_fade_as_they_heat_are_no_braking_rate_nor_low_adhesion(tmp_path, seed,
                                                                          listed):
    """Brakes 40 % (seed 1), 32 % (seed 3) and 35 % (seed 5) weaker once they hold the heat of
    a stop from the top speed, cooling in 88-110 s (bench_foreign --unlisted brake_heat): each
    braking starts strong and ends weak. A braking rate drifting over the run (seed 1, f 0.93
    -> 0.83) and a low-adhesion section over most of the line's brakings (seed 3, x 0.72) were
    confirmed; a braking weaker by the brakes' heat fits the braking better by far, and the
    braking is named as theirs. On seed 5 a 4.3 per mille gradient at one stop was accepted
    beside the braking rate; the heat law takes the braking rate's place in the model the
    gradient is judged in, its cooling fitted again without the gradient: at the comparison's
    120 s the gradient held out at Z 2.0, at 95 s (steps of a quarter) it predicts nothing."""
    rep, eff = _diagnose_foreign(tmp_path, seed, "brake_heat")
    assert eff.brake_heat is not None
    by = {r["cause"]: r for r in rep["ranking"]}
    assert by[listed]["status"] == "not confirmed", by[listed]
    assert by[listed]["why"].startswith("a heat law fits better"), by[listed]["why"]
    assert rep["cause"] == "unexplained", rep["cause"]
    u = rep["unexplained"][0]
    assert u["phase"] == "braking" and u["best_listed"]["cause"] == listed, u
    assert u["size"] > 0, u  # the brakes deliver less than believed


def test_a_strong_remainder_on_a_stretch_is_named_there(tmp_path):
    """A traction cut to 57 % on 2130-2590 m (bench_foreign --unlisted traction_cut, seed 4):
    every family's chi-square is in the thousands. The strongest family is the position
    family; with p-values that underflow to 0 the first family tested (phase) won the tie and
    the remainder was named `all` at every speed, nowhere (core/numerics/tails.py)."""
    rep, eff = _diagnose_foreign(tmp_path, 4, "traction_cut")
    s0, s1, _ = eff.traction_cut
    u = rep["unexplained"][0]
    assert rep["cause"] == "unexplained"
    assert u["phase"] == "traction" and u["where"] is not None, u
    overlap = min(u["where"][1], s1) - max(u["where"][0], s0)
    assert overlap > 0.8 * (s1 - s0) and u["where"][1] - u["where"][0] < 2 * (s1 - s0), u


@pytest.mark.parametrize("seed", [0, 3])
def test_a_balise_reader_that_stamps_late_is_unexplained_with_its_latency(tmp_path, seed):
    """Every balise reading stamped 0.45 s (seed 0) or 0.43 s (seed 3, read at 5-20 m/s only)
    after the train passed the balise (bench_foreign --unlisted balise_late): each lies v x
    delay behind the odometer's track. Before the latency test this was `none` or a listed
    cause in 3 of 8 bags; now the remainder is the reader's latency, with its size in s within
    3 standard errors of the truth, and the summary line says what it is."""
    from train_estimation.tools.diagnose_unexplained import balise_latency, unexplained_line

    rep, eff = _diagnose_foreign(tmp_path, seed, "balise_late")
    assert rep["cause"] == "unexplained", rep["cause"]
    assert not [r for r in rep["ranking"] if r.get("status") == "confirmed"]
    late = [u for u in rep["unexplained"] if balise_latency(u)]
    assert len(late) == 1, rep["unexplained"]
    u = late[0]
    assert u["phase"] == "all" and u["where"] is None and u["when"] is None, u
    lat = rep["evidence"]["_model"]["structure"]["tests"][0]["balise_latency"]
    assert abs(u["size"] - eff.balise_late) <= 3.0 * lat["std_error"], (u["size"], lat)
    assert "stamps late" in unexplained_line(u)


def test_a_balise_off_its_map_position_is_no_low_adhesion_section(tmp_path):
    """A balise read 18 m from where the odometer puts the train (bench_foreign --unlisted
    balise_moved, seed 3) kinks the speed over a few metres, which a low-adhesion section of
    3 m with braking x -4.8 fitted. A section braked over for 0.16 s is below what the data
    resolve, and a negative factor is no adhesion loss: the balise is what is reported."""
    from train_estimation.core.offline.diagnose.causes import adhesion_section as A
    from train_estimation.core.offline.diagnose.result import CauseFit

    rep, eff = _diagnose_foreign(tmp_path, 3, "balise_moved")
    by = {r["cause"]: r for r in rep["ranking"]}
    assert by["adhesion_section"]["status"] != "confirmed", by["adhesion_section"]
    assert rep["cause"] == "unexplained"
    u = rep["unexplained"][0]  # the balise's entry: at one place, the offset as its size
    assert u["where"] is not None and u["where"][0] == u["where"][1], u
    assert abs(abs(u["size"]) - abs(eff.balise_moved[1])) < 3.0, (u, eff.balise_moved)
    fit = CauseFit("adhesion_section", 43.2, {"start": 5213.0, "end": 5216.0,
                                              "factor": -4.765})
    assert "not a low-adhesion section" in A.CAUSE.plausible(fit, None)


def test_a_section_holding_every_stop_is_the_braking_rate(tmp_path):
    """Every brake x 0.82 (bench_foreign braking_rate, seed 100): a low-adhesion section over
    1.3-12.8 km held every stop of the run and scored 2.8 above the braking-rate change by
    leaving out two light brake applications before it. No brake application outside the
    stretch could show the braking normal there, so the section claims nothing more than the
    braking rate, which is named instead (refit.unlocate)."""
    rep, eff = _diagnose_foreign(tmp_path, 100, "braking_rate")
    assert rep["cause"] == "braking_rate", rep["cause"]
    p = rep["parameters"]
    assert abs(p["f_start"] - eff.braking_rate) < 0.02 and abs(p["f_end"] - eff.braking_rate) \
        < 0.02, (p, eff.braking_rate)
    by = {r["cause"]: r for r in rep["ranking"]}
    assert by["adhesion_section"]["status"] == "rejected"
    assert "outside" in by["adhesion_section"]["why"], by["adhesion_section"]


def test_a_section_braked_over_at_the_last_stop_is_held_out_on_its_stretch(tmp_path):
    """Braking x 0.53 on 6960-7262 m (bench_foreign adhesion_section, seed 106): the train stops
    at 7020 m and brakes over the stretch for about 8 s, inside one 30 s block of the held-out
    check; the fold without it fitted another stretch and the check failed for a cause that
    scored 629. A cause at a place is held out in blocks of a quarter of its time on the
    stretch (confirm.place_block): confirmed, on the stretch."""
    rep, eff = _diagnose_foreign(tmp_path, 106, "adhesion_section")
    s0, s1, f = eff.adhesion
    assert rep["cause"] == "adhesion_section", rep["cause"]
    p = rep["parameters"]
    assert s0 - 50 < p["start"] < p["end"] < s1 + 50 and abs(p["factor"] - f) < 0.1, (p, eff)
    held = rep["evidence"]["_model"]["confirmation"]["checks"]["adhesion_section"]["held_out"]
    assert "alternate 30 s" not in held["test"] and held["ok"], held


def test_a_balise_off_its_map_position_misplaces_no_gradient_change(tmp_path):
    """A balise 12.4 m from its map position on metro_demo (bench_foreign --unlisted
    balise_moved, seed 105): it pinned the reference trajectory 12 m off around it, which
    misplaced a gradient change of the map 340 m on, and a -2.4 per mille gradient over 108 m
    there was confirmed beside the balise's entry. The placement now leaves out a fix its
    neighbours contradict (motion.consistent_fixes): only the balise is reported."""
    rep, eff = _diagnose_foreign(tmp_path, 105, "balise_moved")
    assert rep["cause"] == "unexplained", rep["cause"]
    assert not [r for r in rep["ranking"] if r.get("status") == "confirmed"], rep["ranking"][:2]
    u = rep["unexplained"][0]
    assert u["where"] is not None and u["where"][0] == u["where"][1], u
    assert abs(abs(u["size"]) - abs(eff.balise_moved[1])) < 3.0, (u, eff.balise_moved)


@pytest.mark.parametrize("seed,kind", [(3, "none"), (1, "none"), (0, "resistance")])
def test_a_link_with_a_long_latency_tail_changes_nothing(tmp_path, seed, kind):
    """The link's latency 40 ms + Exp(0.5 s) instead of Exp(15 ms): the same readings, only
    logged later. The clock fit puts the mean latency (0.54 s) into the clocks' offset, so the
    commands land that early; the command offset profiled only reached 0.4 s, and the rest
    was read as a traction and a brake delay of +0.16 s (seed 3, `unexplained`). The grid now
    reaches the latency's mean above its floor (motion.shift_grid), and the noise is fitted
    again at the offset found: fitted at the wrong one it was a hundred times too large (seed
    1: an odometer "recalibration" at a creep), and with it a 40 % stronger resistance was
    `none` at a tail of 1.5 s (seed 0)."""
    rep, _ = _diagnose_foreign(tmp_path, seed, kind, tail=0.5 if kind == "none" else 1.5)
    confirmed = [r["cause"] for r in rep["ranking"] if r.get("status") == "confirmed"
                 and r["cause"] != "none"]
    assert rep["cause"] == kind and confirmed == ([] if kind == "none" else [kind]), \
        (rep["cause"], confirmed, rep["unexplained"])


@pytest.mark.parametrize("family", sorted(FS.OTHER_FAMILIES))
def test_lines_and_trains_of_other_families_load_and_run_to_the_last_stop(family, tmp_path):
    """bench_foreign --family: the drawn files are contract files that our loaders read, and
    the foreign driver takes each train from the first station to the last."""
    import bench_foreign as BF
    from train_core.model import load_line, load_train

    for seed in range(3):
        _, paths, line, train, pilot, _ = BF.foreign_case(seed, "none",
                                                          str(tmp_path / f"c{seed}"), family)
        ln, tr = load_line(paths["line"]), load_train(paths["train"])
        assert tr.mass == pytest.approx(train["mass"]) and ln.length == line["length"]
        x, v = pilot[0], pilot[1]
        stops = [s["position"] for s in line["stations"]]
        assert x[-1] == pytest.approx(stops[-1], abs=5.0) and v[-1] < 0.1
        assert v.max() <= line["max_speed"] + 0.5


@pytest.mark.slow
@pytest.mark.parametrize("family,kind", [("freight", "none"), ("freight", "brake_delay"),
                                         ("mountain", "none"), ("mountain", "resistance"),
                                         ("tram", "none"), ("tram", "adhesion_section")])
def test_diagnose_on_lines_and_trains_of_other_families(family, kind, tmp_path):
    """A 2,000 t freight train with a slow air brake, a railcar on a steep line, a tram with a
    stop every 500 m (seed 0 of bench_foreign --family): nothing confirmed on the nominal run,
    the hidden cause confirmed and alone otherwise."""
    rep, _ = _diagnose_foreign(tmp_path, 0, kind, family)
    confirmed = [r["cause"] for r in rep["ranking"] if r["status"] == "confirmed"
                 and r["cause"] != "none"]
    assert rep["cause"] == kind and confirmed == ([] if kind == "none" else [kind]), \
        rep["ranking"][:3]


@pytest.mark.slow
def test_a_weaker_traction_on_a_tram_is_not_a_heavier_train_with_a_stronger_brake(tmp_path):
    """Traction x 0.71 on a tram (bench_foreign --family tram --unlisted, seed 1): a mass x 1.40
    with braking x 1.30 fits it, the two summing to nothing in braking, where the mass change
    has a quarter of its effect (24.5 %): both are not confirmed, the remainder is traction's."""
    rep, eff = _diagnose_foreign(tmp_path, 1, "traction_gain", "tram")
    assert eff.traction_gain == pytest.approx(0.715, abs=0.001)
    st = {r["cause"]: r for r in rep["ranking"]}
    assert rep["cause"] == "unexplained", rep["ranking"][:3]
    for c, other in (("mass", "braking_rate"), ("braking_rate", "mass")):
        assert st[c]["status"] == "not confirmed"
        assert st[c]["why"].startswith(f"cancels with {other} in braking"), st[c]


@pytest.mark.parametrize("kind", ["clock_drift", "clock_step"])
def test_the_estimators_take_a_run_as_the_ground_logged_it(kind):
    """A checker plays the bag into the nodes: the train's own clock (an epoch of 1e8-1e9 s
    against a log time at 1.75e9 s, a drift of 2e-5 to 1e-4 or a step of 0.5-3 s), the link's
    own latency and losses. The robust filter and the KF on a tram run so logged: no
    wrong-side estimate, no bad covariance, available through the step or the drift (but for
    the readings after a step that its burst hypothesis lives on: burst_readings)."""
    import bench_foreign as BF

    from train_estimation.core.online.integrity import IntegrityParams, burst_readings

    rows = BF.run_estimators({"seed": 0, "kind": kind, "family": "tram", "recorded": True,
                              "estimators": ["robust_filter", "kf"]})
    assert [r["estimator"] for r in rows] == ["robust_filter", "kf"]
    for r in rows:
        assert "na" not in r and "exception" not in r, r
        assert r["outputs"] > 1000 and r["wrong_side"] == 0 and r["bad_cov"] == 0, r
        burst = burst_readings(IntegrityParams()) if kind == "clock_step" else 0
        assert r["misleading"] == 0 and r["clear"] >= 0.99 - burst / r["outputs"], r


def test_the_link_s_true_bursts_beside_the_hidden_cause_are_allowed_and_nothing_else():
    import bench_foreign as BF

    def row(kind, reported, confirmed, rc=0):
        return {"kind": kind, "reported": reported, "confirmed": confirmed, "rc": rc}

    assert BF.right_beside_link(row("mass", "mass", ["mass", "bursty_link"]))
    assert BF.right_beside_link(row("mass", "bursty_link", ["bursty_link", "mass"]))
    assert BF.right_beside_link(row("none", "bursty_link", ["bursty_link"]))
    assert BF.right_beside_link(row("none", "none", []))
    assert not BF.right_beside_link(row("mass", "mass", ["mass", "gradient"]))
    assert not BF.right_beside_link(row("mass", "bursty_link", ["bursty_link"]))
    assert not BF.right_beside_link(row("none", "gradient", ["gradient", "bursty_link"]))
    assert not BF.right_beside_link(row("gradient", "unexplained", []))
    assert not BF.right_beside_link(row("mass", "mass", ["mass"], rc=2))


@pytest.mark.slow
def test_a_resistance_that_decays_as_the_train_warms_up_is_no_gradient(tmp_path):
    """An extra resistance of 23 kN decaying with a time constant of 181 s (bench_foreign
    --unlisted, seed 3): over one pass it is a force that falls along the track, which a
    3.7 per mille gradient over the first 2 km and a resistance change for the rest both
    took. A listed cause keeps its size over the time it acts; this gradient's halves fit 4.6
    and 2.8 per mille (z +4.2; before the place causes' halves test its time-span check found
    it needed 1.44 to 0.56 of itself across its stretch), and without it the resistance is not
    one either."""
    rep, eff = _diagnose_foreign(tmp_path, 3, "warmup")
    assert eff.warmup[0] == pytest.approx(181.0, abs=1.0)
    st = {r["cause"]: r for r in rep["ranking"]}
    assert rep["cause"] == "unexplained", rep["ranking"][:3]
    assert not [r for r in rep["ranking"] if r["status"] == "confirmed"], rep["ranking"][:3]
    assert st["gradient"]["why"].startswith("the data's halves fit it differently"), \
        st["gradient"]
    assert rep["unexplained"][0]["phase"] == "all" and rep["unexplained"][0]["when"][0] < 30.0


@pytest.mark.slow
def test_a_radar_odometer_whose_error_grows_with_speed_is_no_odometer_scale(tmp_path):
    """A radar odometer that reads v (1 + k (v / v_top)^2), k -1.7 % (bench_foreign --unlisted
    odometer_speed, seed 0; the square of the speed, not the law diagnose compares with): one
    scale of 0.990 fits it better than none by a score of 12,400 and passed every check. An
    odometer error growing with speed, one parameter as the scale, fits better still (2 ln LR
    +159): not confirmed, and what is left is named on the odometer, of the count's sign."""
    from train_estimation.tools.diagnose_unexplained import on_odometer

    rep, eff = _diagnose_foreign(tmp_path, 0, "odometer_speed")
    st = {r["cause"]: r for r in rep["ranking"]}
    assert st["odometer_scale"]["why"].startswith("a speed law fits better"), st["odometer_scale"]
    assert rep["cause"] == "unexplained", rep["ranking"][:3]
    assert not [r for r in rep["ranking"] if r["status"] == "confirmed"], rep["ranking"][:3]
    u = rep["unexplained"][0]
    assert on_odometer(u) and np.sign(u["size"]) == np.sign(eff.odometer_speed[1]), (u, eff)


@pytest.mark.slow
def test_a_lighter_resistance_on_a_tram_is_fitted_with_a_b_c_nonnegative(tmp_path):
    """A resistance x 0.62 on a tram (bench_foreign --family tram, seed 4: Davis 387 N,
    16 N/(m/s), 1.2 N/(m/s)^2). Below 15 m/s the three terms are nearly collinear: the free fit
    came out as a -251, b 217, c -11.4, a shape the split test contradicted (0.38 to 1.62 of
    itself across the braking command), and the bag was `unexplained`. The data do not need
    the negative terms (2 ln LR 0.8): the best curve with a, b, c >= 0 is the fit, and it is
    confirmed, with the force at the run's speeds near the true one."""
    rep, eff = _diagnose_foreign(tmp_path, 4, "resistance", "tram")
    confirmed = [r["cause"] for r in rep["ranking"] if r["status"] == "confirmed"
                 and r["cause"] != "none"]
    assert rep["cause"] == "resistance" and confirmed == ["resistance"], rep["ranking"][:3]
    p = rep["parameters"]
    assert min(p["a"], p["b"], p["c"]) >= 0.0, p
    a, b, c = eff.davis
    for v in (5.0, 10.0):
        true = a + b * v + c * v * v
        assert abs(p["a"] + p["b"] * v + p["c"] * v * v - true) < 0.15 * true, (p, eff.davis)


@pytest.mark.parametrize("late", [None, 1.0])
def test_a_balise_reader_that_stamps_late_leaves_no_wrong_side_estimate(late):
    """Every balise reading stamped after the train passed the balise (bench_foreign
    --estimators --unlisted balise_late, seed 0): 0.45 s (the drawn effect; 4.5 sds of the
    default prior ``balise_latency_std`` 0.1 s) or 1 s (10 sds). Each fix lies v x delay
    behind the train (15 m at 34 m/s for 0.45 s); taken as the position at its stamp with the
    balise's metre of variance it made 102 and 123 wrong-side estimates here (2,246 of
    158,574 over two seeds and six estimators). The calibration now carries the reader's
    latency: no wrong-side estimate, availability over 99 %, and a reader a second late is
    found out of its prior (event ``balise_latency``) and its latency learnt within 3 sds."""
    import bench_foreign as BF

    rows = BF.run_estimators({"seed": 0, "kind": "balise_late",
                              "estimators": ["robust_filter", "kf"],
                              **({"effect": {"balise_late": late}} if late else {})})
    for r in rows:
        assert "exception" not in r and r["outputs"] > 1000, r
        assert r["wrong_side"] == 0, (r["estimator"], r["wrong_side"])
        assert r["misleading"] == 0 and r["clear"] > 0.99, (r["estimator"], r["clear"])
        if late is not None:
            assert r["events"].get("balise_latency") == 1, r["events"]
            tau, sd = r["balise_latency"]
            assert abs(tau - late) <= 3.0 * sd and sd < 0.1, (tau, sd)


@pytest.mark.parametrize("kind,seed", [("balise_late", 0), ("odometer_scale", 0),
                                       ("balise_moved", 3)])
def test_without_the_distance_a_late_reader_a_wrong_scale_or_a_lying_balise_is_no_hazard(
        kind, seed):
    """``use_distance: false`` (the odometer's speed and the balises; bench_foreign
    --estimators --no-distance): a balise reader stamping 0.45 s late, an odometer whose speed
    is 1-2 % off, or a balise 8-20 m from its map position. With the balises fused as they
    came and the speed as it read, the robust filter made 184 wrong-side estimates on the late
    reader and the KF 6,715; on the scale the KF ran 206 m from the train (495 wrong-side,
    available 13 % of the time: the balises it then met lay outside its gate); the lying
    balise (seed 3) made 42 for the robust filter, 19 with the calibration but no solution
    separation. Now: no wrong-side estimate, and available over 99 % of the time but where a
    balise lies."""
    import bench_foreign as BF

    rows = BF.run_estimators({"seed": seed, "kind": kind,
                              "estimators": ["robust_filter", "kf"],
                              "config": {"use_distance": False}})
    for r in rows:
        assert "exception" not in r and r["outputs"] > 1000, r
        assert r["wrong_side"] == 0, (r["estimator"], r["wrong_side"])
        if kind != "balise_moved":
            assert r["misleading"] == 0 and r["clear"] > 0.99, (r["estimator"], r["clear"])


def test_a_subtle_effect_is_the_plain_draw_at_half_its_deviation():
    """bench_foreign --subtle: the same draw and place as the plain effect, each quantity
    half-way between the believed train and the plain effect (train_sim.cases' subtle size)."""
    import bench_foreign as BF

    d, T = TRAIN["davis"], TRAIN["brake"]["delay"]
    plain = FS.Effect(gradient=(1000.0, 1400.0, -5.0), davis=(1.4 * d["a"], 1.4 * d["b"],
                                                              1.4 * d["c"]),
                      braking_rate=0.8, mass=1.16, odometer_scale=0.98, brake_delay=T + 0.6,
                      clock_drift=8e-5, adhesion=(2000.0, 2300.0, 0.6), p_spec=6.0,
                      traction_delay=T + 0.8, traction_gain=0.7)
    a_max, v_top = TRAIN["performance"]["max_traction"], 20.0
    s = BF.subtle(plain, TRAIN, v_top)
    assert s.gradient == (1000.0, 1400.0, -2.5)
    assert np.allclose(s.davis, (1.2 * d["a"], 1.2 * d["b"], 1.2 * d["c"]), rtol=1e-12)
    assert np.allclose([s.braking_rate, s.mass, s.odometer_scale, s.brake_delay, s.clock_drift,
                        s.adhesion[2], s.p_spec, s.traction_delay],
                       [0.9, 1.08, 0.99, T + 0.3, 4e-5, 0.8, (6.0 + a_max * v_top) / 2, T + 0.4],
                       rtol=1e-12)
    # the power limit's knee half-way between the plain one and the top speed
    assert np.isclose(s.p_spec / a_max, (6.0 / a_max + v_top) / 2, rtol=1e-12)
    assert s.adhesion[:2] == (2000.0, 2300.0)
    assert s.traction_gain == 0.7  # an effect outside the list has one size: left as it is
    assert BF.subtle(FS.Effect(), TRAIN, v_top) == FS.Effect()  # nominal stays nominal


@pytest.mark.parametrize("kind", ["kf", "robust"])
def test_a_command_given_before_the_estimators_start_is_the_one_in_force_at_it(tmp_path, kind):
    """The second simulator's driver gives its first command 45 ms before the odometer's first
    sample, on the reference clock at another epoch than the train's: the commands wait until
    their clock is judged, and the estimators start at the odometer's third sample. A command
    older than the start is the one in force at it: the braking filters refused it as out of
    order in every run of this simulator."""
    import bench_foreign as BF
    from train_core.model import load_line, load_train

    from train_estimation.core.online.estimators import (
        BrakingAdapter,
        BrakingConfig,
        RobustAdapter,
        RobustConfig,
        StartState,
    )
    from train_estimation.tools import faults as F

    _, paths, line_d, train_d, _, eff = BF.foreign_case(0, "none", str(tmp_path / "c"))
    line, train = load_line(str(paths["line"])), load_train(str(paths["train"]))
    sent, truth, clock = [], [], {}
    logged = FS.simulate(line_d, train_d, eff, np.random.default_rng([0, 3]), sent=sent,
                         truth=truth, clock=clock)
    fl = BF.recorded_stream(logged, sent, clock)
    first = next(e for e in fl.events if e[0] == "control")
    assert first[3] < next(e for e in fl.events if e[0] == "odometer")[3]
    st = StartState(float(truth[0][1]))
    a = RobustAdapter(train, line, st, RobustConfig(period=0.1)) if kind == "robust" else \
        BrakingAdapter(train, line, st, BrakingConfig(algorithm=kind))
    _, _, runner = F.run(fl.events, a, 0.1)
    assert not runner.rejected, dict(runner.rejected)
    assert runner.accepted["control"] == sum(1 for e in fl.events if e[0] == "control")


@pytest.mark.parametrize("seed", [0, 2])
def test_an_odometer_whose_speed_lags_its_count_is_unexplained(tmp_path, seed):
    """The odometer's speed readings 0.21 s (seed 0) and 0.21 s (seed 2) behind the train,
    its count on time (bench_foreign --unlisted odometer_lag): the commands' time offset and
    the process noise took it, and the verdict was `none` (7 of seeds 0-7). Its speed readings
    against its own count name it: `unexplained`, the odometer's entry with the lag within 3
    of its standard errors."""
    from train_estimation.tools.diagnose_unexplained import sensor_noise

    rep, eff = _diagnose_foreign(tmp_path, seed, "odometer_lag")
    assert rep["cause"] == "unexplained", rep["cause"]
    assert not [r for r in rep["ranking"] if r.get("status") == "confirmed"]
    sensor = [u for u in rep["unexplained"] if sensor_noise(u)]
    assert len(sensor) == 1 and "behind its own count" in sensor[0]["best_listed"]["why"], \
        rep["unexplained"]
    cc = rep["evidence"]["_model"]["sensors"]["count"]
    assert abs(cc["lag"] - eff.odometer_lag) < 3 * cc["std_error"], (cc, eff.odometer_lag)


@pytest.mark.parametrize("seed", [1, 2])
def test_a_payload_taken_on_at_a_stop_is_no_gradient_and_section(tmp_path, seed):
    """A train 5-12 % heavier from its middle stop on, its brakes not load-weighed
    (bench_foreign --unlisted payload): its traction and braking deliver less from the
    departure after that stop. A gradient over that departure and a low-adhesion section over
    the braking after it were both confirmed (seeds 1 and 2 of a 1.08 payload), each passing
    its own checks. Against a train that changed at a stop (its traction and braking other
    multiples of what is asked from a departure on), the two lose; `unexplained`, no listed
    cause confirmed, and the law's factors within 2 % of 1 / the payload."""
    rep, eff = _diagnose_foreign(tmp_path, seed, "payload")
    assert rep["cause"] == "unexplained", rep["cause"]
    assert not [r for r in rep["ranking"] if r.get("status") == "confirmed"], rep["ranking"]
    laws = [c["stop_law"] for c in rep["evidence"]["_model"]["confirmation"]["checks"].values()
            if "stop_law" in c]
    assert laws, rep["evidence"]["_model"]["confirmation"]["checks"]
    import yaml

    lam = float(yaml.safe_load((tmp_path / "case" / "train.yaml").read_text())
                .get("rotary_allowance", 0.0))
    # the believed effective mass over the true one: the payload is translational mass only
    want = (1.0 + lam) / (lam + eff.payload[1])
    for law in laws:
        assert law["lr"] > 9.0, law
        assert abs(law["traction"] - want) < 0.02 and abs(law["braking"] - want) < 0.02, \
            (law, want)


@pytest.mark.parametrize("seed", [1, 4])
def test_a_balise_map_on_another_datum_than_the_gradients_is_unexplained(tmp_path, seed):
    """Every balise 5.7 m further on (seed 1) or 5.2 m earlier (seed 4) than its telegram and
    the map say, the gradients where the map has them (bench_foreign --unlisted
    balise_datum): each reading agrees with the odometer, so no balise test sees it, and the
    verdict was `none`. The map's gradient changes then act that far from where the balises
    place the run: the datum test names it, `unexplained`, its shift within 3 standard errors
    of the truth."""
    from train_estimation.tools.diagnose_unexplained import datum_shift, unexplained_line

    rep, eff = _diagnose_foreign(tmp_path, seed, "balise_datum")
    assert rep["cause"] == "unexplained", rep["cause"]
    assert not [r for r in rep["ranking"] if r.get("status") == "confirmed"]
    found = [u for u in rep["unexplained"] if datum_shift(u)]
    assert len(found) == 1, rep["unexplained"]
    test = rep["evidence"]["_model"]["structure"]["tests"][0]["datum"]
    assert abs(found[0]["size"] - eff.balise_datum) < 3 * test["std_error"], (test, eff)
    assert "two surveys on two datums" in unexplained_line(found[0])
