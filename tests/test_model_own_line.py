"""A model directory runs on its own line: the stations, start and timetable of the model's
line.yaml, not the scenario's (diagnose's extended model of a run on another line)."""

from __future__ import annotations

import numpy as np
import yaml
from train_core.files import config_file

from train_sim.scenario import load_scenario, with_model
from train_sim.world import simulate

# another line: metro_demo's, stations moved to other level or gentle track (the ATO stops
# within its tolerance there; on a steep grade it may overshoot, which is the driver's matter)
OTHER_STATIONS = [("A", 300.0, 10.0), ("B", 2239.0, 20.0), ("C", 4427.0, 20.0),
                  ("D", 6838.0, 20.0)]


def model_dir(tmp_path, stations):
    line = yaml.safe_load(config_file("lines", "metro_demo").read_text())
    line["stations"] = [{"name": n, "position": x, "dwell": w} for n, x, w in stations]
    d = tmp_path / "model"
    d.mkdir()
    (d / "line.yaml").write_text(yaml.safe_dump(line))
    (d / "train.yaml").write_text(config_file("trains", "metro_b6").read_text())
    return d


def stops(res) -> list[float]:
    """Positions (m) where the train stood still for more than 5 s after moving."""
    t, x, v = (np.asarray(res.truth[k]) for k in ("t", "position", "velocity"))
    rest = v < 1e-3
    out, i = [], 0
    while i < t.size:
        if rest[i]:
            j = i
            while j + 1 < t.size and rest[j + 1]:
                j += 1
            if t[j] - t[i] > 5.0:
                out.append(float(x[i]))
            i = j + 1
        else:
            i += 1
    return out


def test_the_same_line_keeps_the_scenarios_start_and_timetable(tmp_path):
    sc = load_scenario("metro_demo")
    m = with_model(sc, model_dir(tmp_path, [(s.name, s.position, s.dwell)
                                            for s in sc.line.stations]))
    assert m.start_position == sc.start_position and m.timetable == sc.timetable


def test_another_line_runs_its_own_stations_start_and_timetable(tmp_path):
    sc = load_scenario("metro_demo")
    m = with_model(sc, model_dir(tmp_path, OTHER_STATIONS))
    assert m.start_position == OTHER_STATIONS[0][1]
    assert [(s.station, s.position, s.dwell) for s in m.timetable] == OTHER_STATIONS[1:]
    res = simulate(m, duration=560.0)
    got = stops(res)
    # the ATO stops within its stop tolerance of each stopping point of the model's line
    want = [x for _, x, _ in OTHER_STATIONS]
    assert len(got) == len(want), got
    assert np.allclose(got, want, atol=sc.driver.stop_tolerance), (got, want)


def test_a_line_without_stations_starts_on_it_with_no_timetable(tmp_path):
    sc = load_scenario("metro_demo")
    m = with_model(sc, model_dir(tmp_path, []))
    assert m.timetable == () and 0.0 <= m.start_position <= m.line.length
