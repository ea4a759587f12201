"""`csv2bag`: a recorder's CSV into a measured-data bag that check_bag and diagnose accept;
units and clocks converted as stated; bad rows named by line number or skipped and counted."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from train_core.bagio import read_bag

from train_estimation.tools import check_bag, csv2bag
from train_estimation.tools import diagnose as diagnose_tool

REPO = Path(__file__).resolve().parents[1]
EXAMPLE = REPO / "docs" / "examples" / "recorder_log.csv"
MAP = REPO / "docs" / "examples" / "recorder_log.yaml"
CONFIG = REPO / "ros_ws" / "src" / "train_core" / "config"
LINE = CONFIG / "lines" / "metro_demo.yaml"
TRAIN = CONFIG / "trains" / "metro_b6.yaml"

HEADER = "t_ref,t_train_ms,v_kmh,odo_m,balise,trac_pct,brake_pct\n"
ARGS = ["--map", str(MAP), "--line", str(LINE)]


def _csv(tmp_path, rows: list[str]) -> Path:
    p = tmp_path / "log.csv"
    p.write_text(HEADER + "".join(r + "\n" for r in rows))
    return p


def test_units_and_clocks_are_converted_as_stated(tmp_path, capsys):
    log = _csv(tmp_path, ["100.0,5000,36.0,0.0,,50.0,0.0",
                          "100.1,5100,36.0,1.0,2,0.0,25.0",
                          "100.2,5200,18.0,2.0,,0.0,0.0"])
    assert csv2bag.main([str(log), "--out", str(tmp_path / "bag"), *ARGS]) == 0
    assert "odometer 3" in capsys.readouterr().out
    bag = read_bag(tmp_path / "bag")
    odo, bal, ctl = bag.topics["odometer"], bag.topics["balise"], bag.topics["control"]
    # log time = reference clock; odometer and balise stamped by the train clock (ms -> s)
    assert [t for t, _, _ in odo] == [100_000_000_000, 100_100_000_000, 100_200_000_000]
    assert [s for _, s, _ in odo] == pytest.approx([5.0, 5.1, 5.2])
    assert [f["speed"] for _, _, f in odo] == pytest.approx([10.0, 10.0, 5.0])  # km/h -> m/s
    assert [f["seq"] for _, _, f in odo] == [1, 2, 3]
    assert odo[0][2]["speed_variance"] == pytest.approx(0.1 ** 2)
    # control stamped on the reference clock; percent of traction_max 1.0 / braking_max 1.2
    assert [s for _, s, _ in ctl] == pytest.approx([100.0, 100.1, 100.2])
    assert [f["target_acceleration"] for _, _, f in ctl] == pytest.approx([0.5, -0.3, 0.0])
    assert len(bal) == 1 and bal[0][1] == pytest.approx(5.1)
    b2 = [b for b in yaml_balises() if b["id"] == 2][0]
    assert bal[0][2]["balise_id"] == 2 and bal[0][2]["position"] == b2["position"]


def yaml_balises():
    import yaml

    return yaml.safe_load(LINE.read_text())["balises"]


@pytest.mark.parametrize("row,reason", [
    ("100.1,5100,abc,1.0,,0,0", "not a number"),
    ("100.1,5100,36,,,0,0", "no distance"),
    ("100.1,5100,36,nan,,0,0", "distance is nan"),
    ("99.0,5100,36,1.0,,0,0", "not after"),
    ("100.1,5100,36,1.0,,0,-5", "< 0"),
    ("100.1,5100,36,1.0,999,0,0", "balise 999 is not in the line file"),
])
def test_a_bad_row_stops_with_its_line_number_or_is_skipped_and_counted(tmp_path, capsys, row,
                                                                        reason):
    log = _csv(tmp_path, ["100.0,5000,36.0,0.0,,0,0", row, "100.2,5200,36.0,2.0,,0,0"])
    out = tmp_path / "bag"
    assert csv2bag.main([str(log), "--out", str(out), *ARGS]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "line 3" in err and reason in err, err
    assert not out.exists()
    assert csv2bag.main([str(log), "--out", str(out), *ARGS, "--skip-bad-rows"]) == 0
    assert "skipped 1 bad rows" in capsys.readouterr().out
    odo = read_bag(out).topics["odometer"]
    assert [f["seq"] for _, _, f in odo] == [1, 3]  # the skipped row shows as a lost sample


@pytest.mark.parametrize("extra,words", [
    (["--column", "speed=nope"], "no column 'nope' for speed"),
    (["--unit", "speed=mph"], "unit 'mph' for speed"),
    (["--column", "sped=v_kmh"], "unknown quantity 'sped'"),
])
def test_wrong_mapping_gives_one_line_and_exit_2(tmp_path, capsys, extra, words):
    log = _csv(tmp_path, ["100.0,5000,36.0,0.0,,0,0"])
    assert csv2bag.main([str(log), "--out", str(tmp_path / "bag"), *ARGS, *extra]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and words in err, err


@pytest.mark.slow
def test_example_csv_to_bag_then_check_bag_and_diagnose(tmp_path, capsys):
    bag = tmp_path / "bag"
    assert csv2bag.main([str(EXAMPLE), "--out", str(bag), *ARGS]) == 0
    n_rows = len(EXAMPLE.read_text().splitlines()) - 1
    assert f"{n_rows} rows" in capsys.readouterr().out
    s = check_bag.check(str(bag), tmp_path / "check")
    for topic in ("odometer", "balise", "control"):
        assert s["topics"][topic]["count"] > 0 and s["topics"][topic]["non_finite"] == 0
    assert s["topics"]["odometer"]["count"] == n_rows
    rc = diagnose_tool.main(["--bag", str(bag), "--line", str(LINE), "--train", str(TRAIN),
                             "--out", str(tmp_path / "diag"), "--quiet"])
    assert rc == 0
    rep = json.loads((tmp_path / "diag" / "report.json").read_text())
    # a nominal simulated run of the believed train on the believed line
    assert rep["cause"] == "none", rep["ranking"][:3]
