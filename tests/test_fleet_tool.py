"""`fleet` end to end on a small simulated fleet, on a local Dask cluster of two workers.

5 trains x 2 short runs (one stop) on two lines: an unmapped +5 per mille section on the
``north`` line at [1000, 1400) m and degraded brakes (f 0.85 then 0.75) on T01 and T02, plus a
corrupt bag. The report must name the map section (and no other) and exactly the degraded
trains; the corrupt bag is listed with its reason while the others are analysed; a rerun
takes every result from the cache.
"""

import csv
import json
import shutil

import pytest

from train_estimation.tools import fleet as tool
from train_estimation.tools.fleet_dask import diagnosis_row
from train_estimation.tools.fleet_report import failure_groups
from train_estimation.tools.fleet_row import BagRow, consensus_rows
from train_sim.fleet import FleetSpec, write_fleet


@pytest.fixture(scope="module")
def fleet_dir(tmp_path_factory):
    d = tmp_path_factory.mktemp("fleet")
    spec = FleetSpec(trains=5, runs=2, degraded=2, seed=2, stops=1)
    truth = write_fleet(d, spec)
    # a corrupt bag: a real bag's metadata with garbage instead of its MCAP file
    bad = d / "bags" / "T03_corrupt"
    good = d / truth["runs"][0]["bag"]
    shutil.copytree(good, bad)
    for f in bad.glob("*.mcap"):
        f.write_bytes(b"\x89MCAP0\r\n" + bytes(range(256)) * 20)
    with open(d / "manifest.csv", "a", newline="") as fh:
        csv.writer(fh).writerow(["T03", "bags/T03_corrupt", "lines/north.yaml",
                                 "trains/metro_b6.yaml", "99.0"])
    return d, truth


def _bag_rows(csv_rows: list[dict]) -> list[BagRow]:
    """runs.csv's rows as the tool's rows (the columns the failure lines read)."""
    return [BagRow(r["train"], r["bag"], "", "", error=r["error"] or None) for r in csv_rows]


def test_fleet_names_the_map_error_and_the_degraded_trains(fleet_dir, capsys):
    d, truth = fleet_dir
    out = d / "out"
    rc = tool.main(["--manifest", str(d / "manifest.csv"), "--out", str(out), "--workers", "2",
                    "--quiet", "--no-dashboard"])
    assert rc == 0
    res = json.loads((out / "fleet.json").read_text())
    # the map error: one section, on north, where it is hidden
    maps = res["map_errors"]
    assert len(maps) == 1, maps
    m, t = maps[0], truth["map_error"]
    assert m["line"] == t["line"]
    overlap = min(m["end"], t["end"]) - max(m["start"], t["start"])
    assert overlap >= 0.75 * (t["end"] - t["start"]), m
    assert m["ci95"][0] - 1.0 < t["permille"] < m["ci95"][1] + 1.0, m  # size right too
    assert len(m["trains_found"]) >= 3
    # exactly the degraded trains, on the braking rate
    alerted = {a["train"] for a in res["train_alerts"]}
    assert alerted == set(truth["degraded_trains"]), res["train_alerts"]
    assert {a["parameter"] for a in res["train_alerts"]} == {"braking_rate"}
    report = (out / "report.md").read_text()
    assert f"Line north, [{m['start']:.0f}, {m['end']:.0f}) m" in report
    assert "Trains with an alert: **T01, T02**." in report
    # the corrupt bag is reported, the other ten analysed
    rows = list(csv.DictReader(open(out / "runs.csv")))
    assert len(rows) == 11
    bad = [r for r in rows if r["error"]]
    assert [r["bag"].split("/")[-1] for r in bad] == ["T03_corrupt"]
    assert "T03_corrupt" in report and bad[0]["error"] in report
    for png in ("line_north.png", "line_south.png", "trends.png"):
        assert (out / png).stat().st_size > 10_000
    capsys.readouterr()

    # a rerun analyses nothing: every bag's result comes from the cache
    rc = tool.main(["--manifest", str(d / "manifest.csv"), "--out", str(out), "--quiet"])
    assert rc == 0
    assert "11 bags (1 failed), 0 analysed" in capsys.readouterr().out
    rows2 = list(csv.DictReader(open(out / "runs.csv")))
    assert all(r["cached"] == "True" for r in rows2)
    assert json.loads((out / "fleet.json").read_text())["map_errors"] == maps
    # the report's first line says how many bags failed and why
    first = (out / "report.md").read_text().splitlines()[0]
    assert first.endswith(f"1 of 11 bags failed: 1 x {failure_groups(_bag_rows(rows))[0][1][:120]}")
    assert "FAILED" not in first  # 1 of 11 is within --max-failed 0.1
    # more than --max-failed: exit 1, the report written all the same
    rc = tool.main(["--manifest", str(d / "manifest.csv"), "--out", str(out), "--quiet",
                    "--max-failed", "0.05"])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 1 and err[-1].startswith("fleet: 1 of 11 bags failed: 1 x "), err
    assert "(more than --max-failed 0.05)" in err[-1]
    assert (out / "report.md").read_text().startswith("# Fleet report (")
    assert ": FAILED, 1 of 11 bags failed" in (out / "report.md").read_text().splitlines()[0]


def test_second_day_adds_to_the_first(fleet_dir, tmp_path, capsys):
    """The fleet's two days (run 0 on day 1, run 1 and the corrupt bag on day 2) given one
    after the other to the same OUT: the second run analyses only its own bags and the
    consensus is over both days, the same as over both together."""
    d, truth = fleet_dir
    rows = list(csv.DictReader(open(d / "manifest.csv")))
    for name, keep in (("day1.csv", lambda r: float(r["time"]) < 24),
                       ("day2.csv", lambda r: float(r["time"]) >= 24)):
        with open(d / name, "w", newline="") as fh:
            w = csv.DictWriter(fh, fieldnames=list(rows[0]))
            w.writeheader()
            w.writerows([r for r in rows if keep(r)])
    out = tmp_path / "days"
    cache = d / "out" / "cache"  # the first test's results, when it ran (else analysed here)
    common = ["--out", str(out), "--quiet", "--no-dashboard", "--cache", str(cache)]
    assert tool.main(["--manifest", str(d / "day1.csv"), "--day", "2026-11-01"] + common) == 0
    day1 = json.loads((out / "fleet.json").read_text())
    assert day1["run"]["days"] == ["2026-11-01"] and day1["run"]["pool"] == 5
    capsys.readouterr()
    # day 2: 1 of 6 bags fails (> --max-failed 0.1: exit 1), the report is written
    assert tool.main(["--manifest", str(d / "day2.csv"), "--day", "2026-11-02"] + common) == 1
    res = json.loads((out / "fleet.json").read_text())
    assert res["run"]["days"] == ["2026-11-01", "2026-11-02"] and res["run"]["pool"] == 11
    assert len(list(csv.DictReader(open(out / "runs.csv")))) == 6  # the day's bags
    hist = [json.loads(x) for x in (out / "history.jsonl").read_text().splitlines()]
    assert sorted(r["day"] for r in hist) == ["2026-11-01"] * 5 + ["2026-11-02"] * 6
    # the same consensus as over both days at once (days aside)
    from train_estimation.core.offline.fleet import consensus

    both = consensus(consensus_rows([BagRow.from_json(dict(r, day=None)) for r in hist]))
    assert len(both.map_errors) == len(res["map_errors"]) == 1
    m, b = res["map_errors"][0], both.map_errors[0]
    assert (m["start"], m["end"], m["permille"], m["se"]) == \
        (b["start"], b["end"], b["permille"], b["se"])
    assert set(m["days"]) == {"2026-11-01", "2026-11-02"}
    assert m["day_status"] in ("confirmed on 2 days", "unconfirmed"), m
    assert {a["train"] for a in res["train_alerts"]} == \
        {a["train"] for a in both.train_alerts} == set(truth["degraded_trains"])
    report = (out / "report.md").read_text()
    assert "The consensus is over 11 runs of 2 days (2026-11-01 to 2026-11-02)" in report
    # a rerun of day 2 adds nothing twice; --days 1 keeps the latest day only
    tool.main(["--manifest", str(d / "day2.csv"), "--day", "2026-11-02", "--days", "1"]
              + common)
    res = json.loads((out / "fleet.json").read_text())
    assert res["run"]["days"] == ["2026-11-02"] and res["run"]["pool"] == 6
    assert len((out / "history.jsonl").read_text().splitlines()) == 11


def test_fleet_bad_input(tmp_path, capsys):
    assert tool.main(["--manifest", str(tmp_path / "none.csv"), "--out", str(tmp_path)]) == 2
    assert "cannot read the manifest" in capsys.readouterr().err
    (tmp_path / "m.csv").write_text("a,b\n1,2\n")
    assert tool.main(["--manifest", str(tmp_path / "m.csv"), "--out", str(tmp_path)]) == 2
    assert "columns train, bag, line, train_file" in capsys.readouterr().err
    # malformed rows: one line naming the row, exit 2, never a traceback
    head = "train,bag,line,train_file,time\n"
    for body, why in (("T1,bags/a\n", "line 2: no line, train_file"),
                      ("T1,bags/a,l.yaml,t.yaml,1.0,extra\n", "line 2: 6 cells, the header "
                       "has 5"),
                      ("T1,bags/a,l.yaml,t.yaml,1.0\nT2,bags/b,l.yaml,t.yaml,noon\n",
                       "line 3: time 'noon' is not a number"),
                      ("T1,,l.yaml,t.yaml,1.0\n", "line 2: no bag")):
        (tmp_path / "m.csv").write_text(head + body)
        assert tool.main(["--manifest", str(tmp_path / "m.csv"), "--out", str(tmp_path)]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and why in err[0], (err, why)


def test_folder_input_and_cache_key(fleet_dir, tmp_path):
    d, _ = fleet_dir
    tasks = tool.read_folder(str(d / "bags"), str(d / "lines" / "north.yaml"),
                             str(d / "trains" / "metro_b6.yaml"))
    assert len(tasks) == 11
    assert {t["train"] for t in tasks} == {"T01", "T02", "T03", "T04", "T05"}
    # the key follows the bag's content, not its path
    src = d / "bags" / "T01_r0_north"
    copy = tmp_path / "T01" / "run0"
    shutil.copytree(src, copy)
    t = dict(tasks[0], bag=str(src))
    k1 = tool.content_key(t)
    assert tool.content_key(dict(t, bag=str(copy))) == k1
    assert tool.read_folder(str(tmp_path), t["line"], t["train_file"])[0]["train"] == "T01"
    f = next(copy.glob("*.mcap"))
    f.write_bytes(f.read_bytes() + b"\0")
    assert tool.content_key(dict(t, bag=str(copy))) != k1
    assert tool.content_key(dict(t, line=str(d / "lines" / "south.yaml"))) != k1


def test_diagnosis_row_reads_the_typed_result():
    """Each ranked cause gives the fleet its own columns (Cause.fleet_row) from the typed
    diagnosis: an accepted section only, values with a usable standard error only."""
    from pathlib import Path

    from train_core.model import load_train

    from train_estimation.core.offline.diagnose import CauseFit, Diagnosis

    train = load_train(Path(__file__).resolve().parents[1] / "ros_ws" / "src" / "train_core"
                       / "config" / "trains" / "metro_b6.yaml")
    d = train.davis
    ranking = [CauseFit("gradient", 30.0, {"start": 1000.0, "end": 1400.0, "permille": 4.8},
                        extra={"v2": 256.0}),
               CauseFit("braking_rate", 12.0, {"f_start": 0.9, "f_end": 0.8}),
               CauseFit("resistance", -3.0, {"a": d.a + 100.0, "b": d.b, "c": d.c}),
               CauseFit("mass", -5.0, {"mass": 3.0e5}),
               CauseFit("odometer_scale", -6.0, {"scale": 1.001}),
               CauseFit("wheel_slip", -7.0, {"intervals": [[1.0, 2.0]]}),
               CauseFit("none", 0.0, {})]
    evidence = {"gradient": {"std_errors": {"permille": 0.2}},
                "braking_rate": {"std_errors": {"f_start": 0.02, "f_end": 0.04}},
                "resistance": {"std_errors": {"force_at_v_ref": 50.0},
                               "details": {"v_ref": 12.0}},
                "mass": {"std_errors": {"mass": float("nan")}},  # no usable standard error
                "odometer_scale": {"std_errors": {"scale": 3e-4}},
                "_model": {}}
    dg = Diagnosis(cause="gradient", parameters={}, ranking=ranking, untestable=[],
                   evidence=evidence, gain={}, accepted=ranking[:2])
    assert diagnosis_row(dg, train) == {
        "cause": "gradient", "accepted": "gradient+braking_rate",
        "gradient_start": 1000.0, "gradient_end": 1400.0, "gradient_permille": 4.8,
        "gradient_se": 0.2, "gradient_score": 30.0, "gradient_v2": 256.0,
        "braking_rate": pytest.approx(0.85), "braking_rate_se": pytest.approx(0.03),
        "resistance_v_ref": 12.0, "resistance_dforce": pytest.approx(100.0),
        "resistance_dforce_se": 50.0,
        "odometer_scale": 1.001, "odometer_scale_se": 3e-4, "balise": None}
    dg.accepted = ranking[1:2]  # a section ranked but not accepted is no map evidence
    assert not any(k.startswith("gradient") for k in diagnosis_row(dg, train))
    # the balise innovations diagnose kept pass to the row as they are (fleet_readers)
    inn = {"z": [0.5, -1.0], "c": [0.7, 0.6], "info": 1.2, "speed": [10.0, 12.0],
           "position": [100.0, 600.0]}
    evidence["_model"]["balise_readings"] = {"tested": False, "innovations": inn}
    assert diagnosis_row(dg, train)["balise"] == inn


def test_manifest_extra_columns_are_allowed_a_typo_of_an_absent_one_is_not(tmp_path, capsys):
    from train_core.config import ConfigWarning

    head = "train,bag,line,train_file,time,operator,tme\n"
    (tmp_path / "m.csv").write_text(head + "T1,bags/a,l.yaml,t.yaml,1.0,north rail,5\n")
    with pytest.warns(ConfigWarning) as rec:
        tasks = tool.read_manifest(str(tmp_path / "m.csv"))
    texts = " | ".join(str(w.message) for w in rec)
    assert "column 'operator' is ignored" in texts
    assert "column 'tme' is ignored; near: 'time' (given)" in texts
    assert tasks[0]["time"] == 1.0
    # without a time column, 'tme' holding numbers is the time misspelt: the runs' order
    # would silently be lost
    (tmp_path / "m.csv").write_text("train,bag,line,train_file,tme\nT1,bags/a,l.yaml,t.yaml,5\n")
    assert tool.main(["--manifest", str(tmp_path / "m.csv"), "--out", str(tmp_path)]) == 2
    assert "column 'tme': did you mean 'time'?" in capsys.readouterr().err


def test_what_a_person_or_a_spreadsheet_gives_the_fleet_is_read_right(tmp_path, capsys):
    """A manifest saved with a byte-order mark, day labels, a run listed twice, a cache entry
    cut off by a killed run, history values written as text, a line name that is no file name."""
    from pathlib import Path

    from train_estimation.tools.fleet_dask import worker_check

    repo = Path(__file__).resolve().parents[1]
    bag = repo / "bags" / "metro_demo_short"
    conf = repo / "ros_ws" / "src" / "train_core" / "config"
    row = f"{bag},{conf / 'lines' / 'metro_demo.yaml'},{conf / 'trains' / 'metro_b6.yaml'}"
    m = tmp_path / "m.csv"
    m.write_text(f"train,bag,line,train_file,day\nT1,{row},2026-11-8\n", encoding="utf-8-sig")
    assert [t["day"] for t in tool.read_manifest(str(m))] == ["2026-11-08"]
    m.write_text(f"train,bag,line,train_file,day\nT1,{row},30.11.2026\n")
    with pytest.raises(tool.InputError, match="line 2: day '30.11.2026' is not a date"):
        tool.read_manifest(str(m))
    # the same run under two trains: refused before any cluster starts
    m.write_text(f"train,bag,line,train_file\nT2,{row}\nT3,{row}\n")
    assert tool.main(["--manifest", str(m), "--out", str(tmp_path / "o"), "--quiet"]) == 2
    assert "line 3: the same bag as" in capsys.readouterr().err
    # a cache entry cut off mid-write is no entry (the bag is analysed again)
    f = tmp_path / "k.json"
    f.write_text('{"train": "T1", "bag": "x", "line_f')
    assert tool._cached(f) is None
    f.write_text(json.dumps({"train": "T1", "bag": "x", "line_file": "l", "train_file": "t",
                             "braking_rate": "0.60", "braking_rate_se": "0.01"}))
    r = tool._cached(f)
    assert r.braking_rate == 0.6 and r.braking_rate_se == 0.01
    with pytest.raises(ValueError, match="braking_rate 'fast' is not a number"):
        BagRow.from_json({"train": "T1", "bag": "x", "line_file": "l", "train_file": "t",
                          "braking_rate": "fast"})
    assert tool._file_name("S1/S12") == "S1_S12" and tool._file_name("../x") == "_x"
    # the workers' probe without a task the client can see checks the imports only
    assert worker_check({})["problem"] is None
