"""Real lines: TTOBench's track JSON into line.yaml (`python -m train_core.ttobench`).

The track files written here are in TTOBench's schema with invented numbers (the real ones are
not in the repository); the conversion is checked exactly on them, against every rule of the
schema (units, signs, sections), with property tests over random tracks, and the scenarios that
name a real line are checked where its file is (skipped elsewhere with the message that says
where to put it and how to get it)."""

from __future__ import annotations

import json
import math
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest
import yaml
from hypothesis import given, settings
from hypothesis import strategies as st
from train_core import ttobench as T
from train_core.config import ConfigError, ConfigWarning
from train_core.model import line_from_dict, load_line

from train_sim.real_lines import REAL_SCENARIOS, available, hidden_gradient
from train_sim.scenario import load_scenario


def _track(**kw) -> dict:
    """A small invented track in TTOBench's schema: 3 km, stops at 0, 1.2 km and 3 km, speed
    limits in km/h, gradients in per mille, one right curve and one left clothoid."""
    t = {
        "metadata": {"id": "XX_Test_Line", "library version": "TTOBench v1.1",
                     "license": "BSD 2-Clause License"},
        "altitude": {"unit": "m", "value": 400.0},
        "stops": {"unit": "m", "values": [0.0, 1200.0, 3000.0]},
        "speed limits": {"units": {"position": "m", "velocity": "km/h"},
                         "values": [[0.0, 60], [400.0, 90], [2500.0, 72]]},
        "gradients": {"units": {"position": "m", "slope": "permil"},
                      "values": [[0.0, 0.0], [300.0, -12.5], [900.0, 20], [2000.0, 3.0]]},
        "curvatures": {"units": {"position": "m", "radius at start": "m", "radius at end": "m"},
                       "values": [[0.0, "infinity", "infinity"], [500.0, 800.0, 800.0],
                                  [700.0, "infinity", "infinity"],
                                  [1500.0, "infinity", -400.0], [1600.0, -400.0, -400.0],
                                  [1800.0, "infinity", "infinity"]]},
    }
    t.update(kw)
    return t


def test_a_track_converts_exactly():
    line = T.track_to_line(_track(), balise_spacing=500.0, balise_before_stop=40.0)
    assert line["name"] == "XX_Test_Line" and line["length"] == 3000.0
    assert line["stations"] == [{"name": "S1", "position": 0.0, "dwell": 30.0},
                                {"name": "S2", "position": 1200.0, "dwell": 30.0},
                                {"name": "S3", "position": 3000.0, "dwell": 30.0}]
    # km/h -> m/s; the highest limit is the line speed, the others are restrictions
    assert line["max_speed"] == pytest.approx(25.0)
    assert line["speed_limits"] == [{"start": 0.0, "end": 400.0, "speed": pytest.approx(60 / 3.6)},
                                    {"start": 2500.0, "end": 3000.0, "speed": 20.0}]
    # one section per pair, to the next pair or the end; the sign as given (+ = uphill)
    assert line["gradients"] == [{"start": 0.0, "end": 300.0, "permille": 0.0},
                                 {"start": 300.0, "end": 900.0, "permille": -12.5},
                                 {"start": 900.0, "end": 2000.0, "permille": 20.0},
                                 {"start": 2000.0, "end": 3000.0, "permille": 3.0}]
    # straight sections dropped; a clothoid from straight keeps its infinite end as null
    assert line["curves"] == [
        {"start": 500.0, "end": 700.0, "radius_start": 800.0, "radius_end": 800.0},
        {"start": 1500.0, "end": 1600.0, "radius_start": None, "radius_end": -400.0},
        {"start": 1600.0, "end": 1800.0, "radius_start": -400.0, "radius_end": -400.0}]
    # balises: 40 m beyond the origin and before each stop, no two more than 500 m apart
    xs = [b["position"] for b in line["balises"]]
    assert {40.0, 1160.0, 2960.0} <= set(xs) and max(np.diff(xs)) <= 500.0
    assert [b["id"] for b in line["balises"]] == list(range(1, len(xs) + 1))
    # the project's reader takes it, curves and all, without a warning
    with warnings.catch_warnings():
        warnings.simplefilter("error", ConfigWarning)
        ln = line_from_dict(line)
    assert ln.gradient_permille(950.0) == 20.0 and ln.speed_limit(100.0) == pytest.approx(60 / 3.6)


def test_kilometres_and_metres_per_second_are_converted():
    t = _track(stops={"unit": "km", "values": [0, 1.2, 3]},
               **{"speed limits": {"units": {"position": "km", "velocity": "m/s"},
                                   "values": [[0, 20.0], [0.4, 25]]},
                  "gradients": {"units": {"position": "km", "slope": "permil"},
                                "values": [[0, 1.5], [2.25, -1.5]]},
                  "curvatures": {"units": {"position": "km", "radius at start": "km",
                                           "radius at end": "km"},
                                 "values": [[0, 1.2, 1.2], [0.5, "infinity", "infinity"]]}})
    line = T.track_to_line(t)
    assert line["length"] == 3000.0 and line["stations"][1]["position"] == 1200.0
    assert line["max_speed"] == 25.0
    assert line["speed_limits"] == [{"start": 0.0, "end": 400.0, "speed": 20.0}]
    assert line["gradients"][1] == {"start": 2250.0, "end": 3000.0, "permille": -1.5}
    assert line["curves"] == [{"start": 0.0, "end": 500.0, "radius_start": 1200.0,
                               "radius_end": 1200.0}]


def test_a_level_straight_track_has_one_level_section_and_no_curves():
    t = _track()
    del t["gradients"], t["curvatures"]
    line = T.track_to_line(t)
    assert line["gradients"] == [{"start": 0.0, "end": 3000.0, "permille": 0.0}]
    assert "curves" not in line


@pytest.mark.parametrize("change,words", [
    (lambda t: t.pop("stops"), ["missing 'stops'"]),
    (lambda t: t["stops"].update(values=[5.0, 3000.0]), ["stops.values[0]", "must be 0"]),
    (lambda t: t["stops"].update(values=[0.0, 3000.0, 3000.0]), ["strictly increasing"]),
    (lambda t: t["stops"].update(unit="mi"), ["stops", "unit 'mi'", "'km'"]),
    (lambda t: t["speed limits"]["values"].__setitem__(0, [10.0, 60]), ["must be 0"]),
    (lambda t: t["speed limits"]["values"].append([3000.0, 40]), ["not before the track's end"]),
    (lambda t: t["speed limits"]["values"].__setitem__(1, [400.0, 0]), ["must be > 0"]),
    (lambda t: t["speed limits"]["units"].update(velocity="mph"), ["unit 'mph'"]),
    (lambda t: t["gradients"]["values"].__setitem__(2, [200.0, 5.0]), ["strictly increasing"]),
    (lambda t: t["gradients"]["values"].__setitem__(2, [900.0, 75.0]), ["+-60 per mille"]),
    (lambda t: t["gradients"]["units"].update(slope="%"), ["unit '%'", "'permil'"]),
    (lambda t: t["gradients"]["values"].__setitem__(1, [300.0]), ["a list of 2"]),
    (lambda t: t["gradients"]["values"].__setitem__(1, [300.0, "steep"]), ["finite number"]),
    (lambda t: t["curvatures"]["values"].__setitem__(1, [500.0, "tight", 800.0]),
     ["\"infinity\""]),
    (lambda t: t["curvatures"]["values"].__setitem__(1, [500.0, 0, 800.0]), ["radius of 0"]),
    (lambda t: t["metadata"].pop("id"), ["metadata", "'id'"]),
    (lambda t: t["speed limits"]["values"].__setitem__(1, [400.0, 1e308]),
     ["faster than any railway", "check its unit"]),
    (lambda t: t["stops"].update(values=[0.0, 1e12]), ["more than 100,000 balises"]),
])
def test_a_track_outside_the_schema_is_refused_naming_the_field(change, words):
    t = _track()
    change(t)
    with pytest.raises(ConfigError) as e:
        T.track_to_line(t, where="t.json")
    for w in words:
        assert w in str(e.value), (w, str(e.value))


def test_a_field_outside_the_schema_is_named_in_a_warning():
    with pytest.warns(ConfigWarning, match="'tunnels'"):
        T.track_to_line(_track(tunnels=[]))
    t = _track()
    t["stops"]["note"] = "surveyed 2019"  # inside a field too: named, not refused
    with pytest.warns(ConfigWarning, match="stops: keys outside TTOBench's schema.*'note'"):
        assert T.track_to_line(t)["length"] == 3000.0


def test_a_header_value_with_a_newline_stays_a_comment_and_a_bom_is_read(tmp_path, capsys):
    t = _track()
    t["metadata"]["created by"] = "A. Person\nmax_speed: 1"
    src = tmp_path / "XX_Test_Line.json"
    src.write_text(json.dumps(t), encoding="utf-8-sig")
    assert T.main([str(src), "--out", str(tmp_path / "line.yaml")]) == 0
    line = load_line(tmp_path / "line.yaml")
    assert line.max_speed == pytest.approx(25.0)  # the header's text is no key
    assert "created by A. Person max_speed: 1)" in (tmp_path / "line.yaml").read_text()


# ------------------------------------------------------------------------------------------------
# Properties over random tracks
# ------------------------------------------------------------------------------------------------

@st.composite
def tracks(draw):
    n_stops = draw(st.integers(2, 6))
    gaps = draw(st.lists(st.integers(200, 4000), min_size=n_stops - 1, max_size=n_stops - 1))
    stops = [0.0] + list(np.cumsum(gaps).astype(float))
    length = stops[-1]

    def sections(values):
        k = draw(st.integers(1, 8))
        cuts = sorted(set(draw(st.lists(st.integers(1, int(length) - 1), min_size=k - 1,
                                        max_size=k - 1))))
        pos = [0.0] + [float(c) for c in cuts]
        vals = [draw(values)]
        for _ in pos[1:]:
            vals.append(draw(values.filter(lambda v, p=vals[-1]: v != p)))
        return [[p, v] for p, v in zip(pos, vals)]

    grads = sections(st.floats(-40, 40, allow_nan=False).map(lambda x: round(x, 1)))
    limits = sections(st.integers(30, 160))
    return {"metadata": {"id": "XX_Random", "library version": "TTOBench v1.1"},
            "stops": {"unit": "m", "values": stops},
            "speed limits": {"units": {"position": "m", "velocity": "km/h"}, "values": limits},
            "gradients": {"units": {"position": "m", "slope": "permil"}, "values": grads}}


def _at(pairs, x):
    """TTOBench's value at x: the last pair starting at or before x."""
    return [v for p, v in pairs if p <= x][-1]


@settings(max_examples=60, deadline=None)
@given(tracks(), st.floats(100.0, 2000.0))
def test_properties_of_the_converted_line(track, spacing):
    line = T.track_to_line(track, balise_spacing=spacing)
    ln = line_from_dict(line)
    length = track["stops"]["values"][-1]
    assert line["length"] == length
    # gradient sections: contiguous from 0 to the end, their lengths add up to the line's
    g = line["gradients"]
    assert g[0]["start"] == 0.0 and g[-1]["end"] == length
    assert all(a["end"] == b["start"] for a, b in zip(g, g[1:]))
    assert math.isclose(sum(s["end"] - s["start"] for s in g), length)
    # at every section's start, its middle and just before its end: the file's value and sign
    xs = [x for s in g for x in (s["start"], (s["start"] + s["end"]) / 2, s["end"] - 1e-3)]
    for x in xs:
        assert ln.gradient_permille(x) == pytest.approx(_at(track["gradients"]["values"], x))
        assert ln.speed_limit(x) == pytest.approx(
            _at(track["speed limits"]["values"], x) / 3.6, rel=1e-6)
    # speed restrictions: within the line, below the line speed, which is the highest limit
    assert line["max_speed"] == pytest.approx(
        max(v for _, v in track["speed limits"]["values"]) / 3.6, rel=1e-6)
    for s in line["speed_limits"]:
        assert 0 <= s["start"] < s["end"] <= length and s["speed"] < line["max_speed"]
    # one station per stop; balises sorted, unique, on the line, never further apart than asked
    assert [s["position"] for s in line["stations"]] == track["stops"]["values"]
    b = [x["position"] for x in line["balises"]]
    assert b == sorted(set(b)) and 0 <= b[0] and b[-1] <= length
    assert np.all(np.diff(b) <= spacing + 1e-6)


# ------------------------------------------------------------------------------------------------
# The command and the scenarios
# ------------------------------------------------------------------------------------------------

def test_the_command_writes_line_yaml_and_refuses_bad_input_with_exit_2(tmp_path, capsys):
    src = tmp_path / "XX_Test_Line.json"
    src.write_text(json.dumps(_track()))
    assert T.main([str(src), "--out", str(tmp_path / "line.yaml")]) == 0
    out = capsys.readouterr().out
    assert "3000 m, 3 stations, 4 gradient sections (-12.5 to +20 per mille)" in out
    text = (tmp_path / "line.yaml").read_text()
    assert "TTOBench" in text.splitlines()[1] and "BSD 2-Clause" in text
    assert load_line(tmp_path / "line.yaml").length == 3000.0
    (tmp_path / "bad.json").write_text("{not json")
    assert T.main([str(tmp_path / "bad.json"), "--out", str(tmp_path / "x.yaml")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("ttobench2line: ") and "not JSON" in err and len(err.splitlines()) == 1
    assert not (tmp_path / "x.yaml").exists()


def test_the_module_command_answers_help(ros_env):
    """The importer runs as ``python -m train_core.ttobench`` (not a package executable: the
    interface's executables are a fixed list)."""
    r = subprocess.run([sys.executable, "-m", "train_core.ttobench", "--help"],
                       capture_output=True, text=True, env=ros_env, timeout=60)
    assert r.returncode == 0 and "TTOBench" in r.stdout and "--balise-spacing" in r.stdout


def _scenario(tmp_path: Path, track_id: str) -> Path:
    p = tmp_path / "sc.yaml"
    p.write_text(yaml.safe_dump({
        "name": "real", "line": f"ttobench:{track_id}", "train": "metro_b6", "duration": 120.0,
        "start": {"position": 0.0}, "timetable": [{"station": "S2"}]}))
    return p


def test_a_scenario_finds_its_line_in_the_directory_named_at_run_time(tmp_path, monkeypatch):
    d = tmp_path / "lines"
    d.mkdir()
    (d / "XX_Test_Line.json").write_text(json.dumps(_track()))
    monkeypatch.setenv(T.LINES_ENV, str(d))
    monkeypatch.setattr(T, "cache_dir", lambda: tmp_path / "cache")
    sc = load_scenario(_scenario(tmp_path, "XX_Test_Line"))
    assert sc.line.length == 3000.0 and sc.timetable[0].position == 1200.0
    assert Path(sc.line_path).parent == tmp_path / "cache"
    # converted once: the same file again, a new one when the track changes
    assert T.resolve_line("XX_Test_Line") == Path(sc.line_path)
    (d / "XX_Test_Line.json").write_text(json.dumps(_track(stops={"unit": "m", "values": [
        0.0, 1200.0, 3100.0]})))
    assert T.resolve_line("XX_Test_Line") != Path(sc.line_path)


def test_an_absent_line_says_where_to_put_it_and_how_to_get_it(tmp_path, monkeypatch):
    monkeypatch.setattr(T, "search_dirs", lambda: [tmp_path / "none"])
    with pytest.raises(ConfigError) as e:
        load_scenario(_scenario(tmp_path, "CN_Songjiazhuang_Yizhuang"))
    msg = str(e.value)
    for w in (str(tmp_path / "none" / "CN_Songjiazhuang_Yizhuang.json"), T.LINES_ENV,
              "github.com/dkouzoup/TTOBench", "tracks/CN_Songjiazhuang_Yizhuang.json"):
        assert w in msg, (w, msg)


def test_the_demo_on_an_absent_real_line_exits_2_with_that_message(tmp_path, monkeypatch,
                                                                    capsys):
    from train_bringup import main_job

    monkeypatch.setattr(T, "search_dirs", lambda: [tmp_path / "none"])
    assert main_job.main(["--scenario", "yizhuang_metro", "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "CN_Songjiazhuang_Yizhuang.json" in err and "TTOBench" in err


# ------------------------------------------------------------------------------------------------
# The real lines, where their files are (../shared/lines/ or $TRAIN_LINES_DIR)
# ------------------------------------------------------------------------------------------------

REAL, MISSING = available()
# what TTOBench's tracks.csv states of each (length m, stops, gradient range per mille)
STATED = {"yizhuang_metro": (22728.0, 14, -24.0, 24.0),
          "zurich_stadelhofen": (5790.0, 4, -38.0, 28.0)}


def _real(name):
    return pytest.param(name, marks=pytest.mark.skipif(
        name not in REAL, reason=MISSING.get(name, "")))


@pytest.mark.parametrize("name", [_real(n) for n in REAL_SCENARIOS])
def test_a_real_line_is_what_ttobench_states(name):
    sc = REAL[name]
    length, n_stops, gmin, gmax = STATED[name]
    g = [s.permille for s in sc.line.gradients]
    assert sc.line.length == length and len(sc.line.stations) == n_stops
    assert (min(g), max(g)) == (gmin, gmax)
    assert len(sc.timetable) == n_stops - 1


@pytest.mark.slow
@pytest.mark.parametrize("name", [_real("zurich_stadelhofen")])
def test_a_hidden_gradient_on_a_real_line_is_found(name, tmp_path, capsys):
    """The steep Swiss line (221 mapped sections, -38 to +28 per mille), run whole: a map error
    of 4-8 per mille over 300-700 m between two stops is confirmed where it is."""
    from train_estimation.tools import diagnose as tool
    from train_sim.generate import generate

    sc = REAL[name]
    hg = hidden_gradient(sc, np.random.default_rng([1, 7]))
    generate(hg.scenario, tmp_path / "bag", measured=True)
    assert tool.main(["--bag", str(tmp_path / "bag"), "--line", sc.line_path, "--train",
                      sc.train_path, "--out", str(tmp_path / "d"), "--quiet",
                      "--no-plots"]) == 0
    rep = json.loads((tmp_path / "d" / "report.json").read_text())
    assert rep["cause"] == "gradient", rep["ranking"][:3]
    p = rep["parameters"]
    overlap = min(p["end"], hg.end) - max(p["start"], hg.start)
    assert overlap >= 0.75 * (hg.end - hg.start), (p, hg)
    # the size: the fitted edges lie tens of metres from the true ones (one second of running
    # at 10-30 m/s), which moves the size by their share of the section, not by its noise
    se = rep["evidence"]["gradient"]["std_errors"]["permille"]
    share = abs((p["end"] - p["start"]) - (hg.end - hg.start)) / (hg.end - hg.start)
    assert abs(p["permille"] - hg.permille) < 4 * se + share * abs(hg.permille) + 0.05 * abs(
        hg.permille), (p, hg, se)
