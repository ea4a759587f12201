"""`csv2bag`: a recorder's CSV into a measured-data bag that check_bag and diagnose accept;
units and clocks converted as stated; bad rows named by line number or skipped and counted."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
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


def _rows10(bad_at: int | None = None, bad: str = "") -> list[str]:
    """Ten samples 0.1 s apart (train clock in ms), the ``bad_at``-th replaced by ``bad``."""
    rows = [f"{100 + i / 10:.1f},{5000 + 100 * i},36.0,{float(i):.1f},,0,0" for i in range(10)]
    if bad_at is not None:
        rows[bad_at] = bad
    return rows


@pytest.mark.parametrize("row,reason", [
    ("100.4,5400,abc,4.0,,0,0", "not a number"),
    ("100.4,5400,36,,,0,0", "no distance"),
    ("100.4,5400,36,nan,,0,0", "distance is nan"),
    ("99.0,5400,36,4.0,,0,0", "before the previous row's"),
    ("100.4,5400,36,4.0,,0,-5", "< 0"),
    ("100.4,5400,36,4.0,999,0,0", "balise 999 is not in the line file"),
    ("100.4,,36,4.0,,0,0", "no train_time value"),
])
def test_a_bad_row_stops_with_its_line_number_or_is_skipped_and_counted(tmp_path, capsys, row,
                                                                        reason):
    log = _csv(tmp_path, _rows10(4, row))
    out = tmp_path / "bag"
    assert csv2bag.main([str(log), "--out", str(out), *ARGS]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "line 6" in err and reason in err, err
    assert not out.exists()
    assert csv2bag.main([str(log), "--out", str(out), *ARGS, "--skip-bad-rows"]) == 0
    text = capsys.readouterr().out
    assert "skipped 1 bad rows" in text
    odo = read_bag(out).topics["odometer"]
    # the skipped row shows as a lost sample, numbered from the train clock's period
    assert [f["seq"] for _, _, f in odo] == [1, 2, 3, 4, 6, 7, 8, 9, 10]
    assert "9 of 10 in the log, 1 lost (10.0 %) in 1 gaps" in text, text


def test_mass_skipping_is_an_error_with_the_reasons(tmp_path, capsys):
    # a column in the wrong unit or format: every other row bad, far beyond 1 %
    rows = _rows10()
    rows[1::2] = [r.replace(",36.0,", ",fast,") for r in rows[1::2]]
    log = _csv(tmp_path, rows)
    out = tmp_path / "bag"
    assert csv2bag.main([str(log), "--out", str(out), *ARGS, "--skip-bad-rows"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1, err
    assert "5 of 10 rows would be skipped (not_a_number 5)" in err, err
    assert "more than --max-skipped 1% (1 rows)" in err, err
    assert not out.exists()
    assert csv2bag.main([str(log), "--out", str(out), *ARGS, "--skip-bad-rows",
                         "--max-skipped", "50%"]) == 0
    assert csv2bag.main([str(log), "--out", str(tmp_path / "b2"), *ARGS, "--skip-bad-rows",
                         "--max-skipped", "4"]) == 2
    assert "more than --max-skipped 4 (4 rows)" in capsys.readouterr().err


def test_the_examples_missing_samples_are_counted_and_located(tmp_path, capsys):
    """docs/examples/recorder_log.csv lacks 356 of its 3001 samples: the bag says so (its seq
    has the gaps) and so does check_bag's received fraction."""
    import csv as csvmod

    bag = tmp_path / "bag"
    assert csv2bag.main([str(EXAMPLE), "--out", str(bag), *ARGS]) == 0
    out = capsys.readouterr().out
    rows = list(csvmod.DictReader(EXAMPLE.open()))
    t_ms = [int(r["t_train_ms"]) for r in rows]
    spanned = (t_ms[-1] - t_ms[0]) // 100 + 1  # the train samples every 100 ms
    assert spanned - len(rows) == 356 and spanned == 3001
    assert f"{len(rows)} of 3001 in the log, 356 lost (11.9 %)" in out, out
    assert "period 0.1 s" in out, out
    seq = [f["seq"] for _, _, f in read_bag(bag).topics["odometer"]]
    assert seq == [(t - t_ms[0]) // 100 + 1 for t in t_ms]
    s = check_bag.check(str(bag), tmp_path / "check")
    received = s["topics"]["odometer"]["received_fraction"]
    assert received == pytest.approx(len(rows) / 3001, abs=1e-3)


def test_a_sample_counter_column_numbers_the_samples(tmp_path, capsys):
    p = tmp_path / "log.csv"
    p.write_text("t,n,v,d\n0.0,17,1.0,0.0\n0.1,18,1.0,0.1\n0.35,21,1.0,0.35\n")
    assert csv2bag.main([str(p), "--out", str(tmp_path / "bag"), "--column", "time=t",
                         "--column", "sample=n", "--column", "speed=v",
                         "--column", "distance=d"]) == 0
    out = capsys.readouterr().out
    assert "numbered by the log's sample counter: 3 of 5 in the log, 2 lost" in out, out
    assert "2 before line 4" in out, out
    odo = read_bag(tmp_path / "bag").topics["odometer"]
    assert [f["seq"] for _, _, f in odo] == [17, 18, 21]


def test_a_sample_counter_that_wraps_or_restarts_loses_nothing_by_it(tmp_path, capsys):
    """A uint32 counter wraps past 2^32 - 1 to 0: no sample lost (before: 4,294,967,293 of
    4,294,967,296 lost). A counter that starts again from 0 while the train clock runs on (a
    recorder restarted) counts its runs apart: only the samples missing within them are lost."""
    p = tmp_path / "log.csv"
    wrap = [2 ** 32 - 2, 2 ** 32 - 1, 0, 1, 3]  # 2 missing after the wrap
    p.write_text("t,n,v,d\n" + "".join(f"{0.1 * i:.1f},{n},1.0,{0.1 * i:.1f}\n"
                                       for i, n in enumerate(wrap)))
    cols = ["--column", "time=t", "--column", "sample=n", "--column", "speed=v",
            "--column", "distance=d"]
    assert csv2bag.main([str(p), "--out", str(tmp_path / "bag"), *cols]) == 0
    out = capsys.readouterr().out
    assert "5 of 6 in the log, 1 lost (16.7 %) in 1 gaps" in out, out
    assert [f["seq"] for _, _, f in read_bag(tmp_path / "bag").topics["odometer"]] == wrap
    p.write_text("t,n,v,d\n" + "".join(f"{0.1 * i:.1f},{n},1.0,{0.1 * i:.1f}\n"
                                       for i, n in enumerate([40, 41, 43, 0, 1, 2, 4])))
    assert csv2bag.main([str(p), "--out", str(tmp_path / "bag2"), *cols]) == 0
    out = capsys.readouterr().out
    assert "7 of 9 in the log, 2 lost (22.2 %) in 2 gaps; the counter restarted 1 time" in out, \
        out


def test_period_numbering_counts_whole_periods_without_drifting():
    # 0.1 s sampling, 10 000 samples with 1 000 lost at random, stamps with 1 ms jitter
    rng = np.random.default_rng(3)
    n = 10_000
    keep = np.sort(rng.choice(np.arange(1, n), size=n - 1_001, replace=False))
    keep = np.concatenate([[0], keep])
    stamps = 1234.5 + 0.1 * keep + rng.uniform(-1e-3, 1e-3, keep.size)
    period = csv2bag.sampling_period(stamps)
    assert abs(period - 0.1) < 1e-6
    seq = csv2bag.number_samples(stamps, period)
    assert np.array_equal(seq, keep + 1)


def test_samples_delivered_out_of_order_or_twice_keep_their_numbers(tmp_path, capsys):
    """A link with jitter delivers samples out of order and the log keeps the arrival order;
    a sample delivered twice keeps its number (a duplicate), and only the missing one is lost."""
    assert list(csv2bag.number_samples([10.0, 10.2, 10.1, 10.4, 10.4], 0.1)) == [1, 3, 2, 5, 5]
    p = tmp_path / "log.csv"
    p.write_text("t,tt,v,d\n" + "".join(f"{100 + i * 0.1:.1f},{tt},1.0,{tt}\n" for i, tt in
                                       enumerate([10.0, 10.2, 10.1, 10.4, 10.4, 10.5])))
    assert csv2bag.main([str(p), "--out", str(tmp_path / "bag"), "--column", "time=t",
                         "--column", "train_time=tt", "--column", "speed=v",
                         "--column", "distance=d"]) == 0
    out = capsys.readouterr().out
    assert "5 of 6 in the log, 1 lost (16.7 %) in 1 gaps" in out, out
    assert [f["seq"] for _, _, f in read_bag(tmp_path / "bag").topics["odometer"]] == \
        [1, 3, 2, 5, 5, 6]


def test_rows_with_commands_only_and_balise_rows(tmp_path):
    p = tmp_path / "log.csv"
    p.write_text(HEADER + "".join(r + "\n" for r in [
        "100.0,5000,36.0,0.0,,,",          # a sample without a command
        "100.05,,,,,50.0,",                 # a command alone (no train time needed)
        "100.1,5100,36.0,1.0,,,",
        "100.12,5120,,,2,,",                # a balise passage alone
        "100.2,5200,36.0,2.0,,,25.0"]))      # a sample and a command
    assert csv2bag.main([str(p), "--out", str(tmp_path / "bag"), *ARGS]) == 0
    bag = read_bag(tmp_path / "bag")
    ctl = bag.topics["control"]
    assert [f["target_acceleration"] for _, _, f in ctl] == pytest.approx([0.5, -0.3])
    assert [t for t, _, _ in ctl] == [100_050_000_000, 100_200_000_000]
    assert [f["seq"] for _, _, f in bag.topics["odometer"]] == [1, 2, 3]
    (b,) = bag.topics["balise"]
    assert b[1] == pytest.approx(5.12) and b[2]["balise_id"] == 2


@pytest.mark.parametrize("fmt", ["iso", "iso_z", "iso_offset", "of_day", "of_day_numbers"])
def test_iso_8601_and_times_of_day_across_midnight(tmp_path, capsys, fmt):
    """A log from 23:59:59.7 to 00:00:00.3: the times keep increasing through midnight."""
    from datetime import datetime, timedelta, timezone

    t0 = datetime(2026, 11, 30, 23, 59, 59, 700000, tzinfo=timezone.utc)
    times = [t0 + timedelta(seconds=0.1 * i) for i in range(7)]
    cell = {"iso": lambda t: t.replace(tzinfo=None).isoformat(timespec="milliseconds"),
            "iso_z": lambda t: t.isoformat(timespec="milliseconds").replace("+00:00", "Z"),
            "iso_offset": lambda t: t.astimezone(timezone(timedelta(hours=1))).isoformat(),
            "of_day": lambda t: t.strftime("%H:%M:%S.%f")[:-3],
            "of_day_numbers": lambda t: "%.1f" % (t.hour * 3600 + t.minute * 60 + t.second
                                                  + t.microsecond / 1e6)}[fmt]
    p = tmp_path / "log.csv"
    p.write_text("when,v,d\n" + "".join(f"{cell(t)},1.0,{0.1 * i:.1f}\n"
                                         for i, t in enumerate(times)))
    assert csv2bag.main([str(p), "--out", str(tmp_path / "bag"), "--column", "time=when",
                         "--column", "speed=v", "--column", "distance=d"]) == 0
    out = capsys.readouterr().out
    odo = read_bag(tmp_path / "bag").topics["odometer"]
    stamps = np.array([s for _, s, _ in odo])
    assert np.allclose(np.diff(stamps), 0.1, atol=1e-5), stamps
    assert [f["seq"] for _, _, f in odo] == list(range(1, 8))
    if fmt.startswith("iso"):
        assert stamps[0] == pytest.approx(t0.timestamp(), abs=1e-5)
        assert "midnight" not in out
    else:
        assert stamps[0] == pytest.approx(86399.7, abs=1e-5)
        assert "time crossed midnight at line 5" in out, out


def test_rows_out_of_order_are_refused_or_sorted(tmp_path, capsys):
    rows = _rows10()
    rows[3], rows[4] = rows[4], rows[3]
    log = _csv(tmp_path, rows)
    assert csv2bag.main([str(log), "--out", str(tmp_path / "bag"), *ARGS]) == 2
    assert "--sort sorts them by time" in capsys.readouterr().err
    assert csv2bag.main([str(log), "--out", str(tmp_path / "bag"), *ARGS, "--sort"]) == 0
    assert "--sort moved 2 rows into time order" in capsys.readouterr().out
    odo = read_bag(tmp_path / "bag").topics["odometer"]
    assert [f["seq"] for _, _, f in odo] == list(range(1, 11))
    assert [f["distance"] for _, _, f in odo] == pytest.approx([float(i) for i in range(10)])


def test_extra_keys_in_the_map_file_are_named_not_refused(tmp_path, capsys):
    m = tmp_path / "map.yaml"
    m.write_text(MAP.read_text() + "recorder: DR-500\nspeed_sd: 0.2\n")
    log = _csv(tmp_path, _rows10())
    assert csv2bag.main([str(log), "--out", str(tmp_path / "bag"), "--map", str(m),
                         "--line", str(LINE)]) == 0
    err = capsys.readouterr().err
    assert "unknown key 'recorder' is ignored" in err
    assert "unknown key 'speed_sd' is ignored; near: 'speed_std' (given)" in err


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
    # 356 of the 3001 samples are not in the log
    assert s["topics"]["odometer"]["received_fraction"] < 0.9
    rc = diagnose_tool.main(["--bag", str(bag), "--line", str(LINE), "--train", str(TRAIN),
                             "--out", str(tmp_path / "diag"), "--quiet"])
    assert rc == 0
    rep = json.loads((tmp_path / "diag" / "report.json").read_text())
    # a nominal simulated run of the believed train on the believed line
    assert rep["cause"] == "none", rep["ranking"][:3]


def _bag_topics(path) -> dict:
    return {k: list(v) for k, v in read_bag(path).topics.items()}


def _export(rows: list[str], sep: str, comma_decimal: bool) -> list[str]:
    """The example's rows as another spreadsheet writes them: its separator, and 0,36 for 0.36
    where the comma is the decimal mark."""
    return [r.replace(",", sep).replace(".", ",") if comma_decimal else r.replace(",", sep)
            for r in rows]


@pytest.mark.parametrize("form", ["excel_de", "bom_crlf", "tab", "bar", "quoted"])
def test_every_common_csv_form_gives_the_same_bag(tmp_path, capsys, form):
    """One log written as spreadsheets and recorders write CSV: a German Excel export (UTF-8
    byte-order mark, Windows line ends, ``;`` separators and decimal commas), a UTF-8 export
    with a BOM, tab- and bar-separated text, quoted cells with a space after each comma: the
    same bag as the plain form, with what was found said where it is not the plain form."""
    rows = [HEADER.strip()] + _rows10() + ["101.0,6000,36.0,10.5,2,0,25"]
    plain = tmp_path / "plain.csv"
    plain.write_text("\n".join(rows) + "\n")
    assert csv2bag.main([str(plain), "--out", str(tmp_path / "ref"), *ARGS]) == 0
    assert "read with" not in capsys.readouterr().out
    text, said = {
        "excel_de": ("\ufeff" + "\r\n".join(_export(rows, ";", True)) + "\r\n", "';' and the "
                     "decimal mark ','"),
        "bom_crlf": ("\ufeff" + "\r\n".join(rows) + "\r\n", None),
        "tab": ("\n".join(_export(rows, "\t", False)) + "\n", "'\\t'"),
        "bar": ("\n".join(_export(rows, "|", False)) + "\n", "'|'"),
        "quoted": ("\n".join(", ".join(f'"{c}"' for c in r.split(",")) for r in rows) + "\n",
                   None),
    }[form]
    log = tmp_path / "log.csv"
    log.write_bytes(text.encode("utf-8"))
    assert csv2bag.main([str(log), "--out", str(tmp_path / "bag"), *ARGS]) == 0
    out = capsys.readouterr().out
    assert (said is None) == ("read with" not in out) and (said is None or said in out), out
    assert _bag_topics(tmp_path / "bag") == _bag_topics(tmp_path / "ref")


def test_a_stated_format_is_used_and_text_in_another_encoding_says_what_to_do(tmp_path,
                                                                              capsys):
    """A Latin-1 (cp1252) export with an accented column name stops with the byte where
    UTF-8 failed and the option that fixes it; stated, it converts. A stated delimiter is
    used as stated (a comma-separated file read with ``;`` has no columns)."""
    rows = ["t_ref;t_train_ms;vitesse_km/h_équiv;odo_m"] + \
        [f"{100 + i / 10:.1f};{5000 + 100 * i};36.0;{i}.0".replace(".", ",") for i in range(10)]
    log = tmp_path / "log.csv"
    log.write_bytes(("\r\n".join(rows) + "\r\n").encode("cp1252"))
    args = [str(log), "--column", "time=t_ref", "--column", "train_time=t_train_ms",
            "--unit", "train_time=ms", "--column", "speed=vitesse_km/h_équiv",
            "--unit", "speed=km/h", "--column", "distance=odo_m"]
    assert csv2bag.main([*args, "--out", str(tmp_path / "a")]) == 2
    err = capsys.readouterr().err
    assert "not utf-8 text" in err and "--encoding cp1252" in err, err
    assert csv2bag.main([*args, "--out", str(tmp_path / "b"), "--encoding", "cp1252"]) == 0
    odo = read_bag(tmp_path / "b").topics["odometer"]
    assert [f["speed"] for _, _, f in odo] == pytest.approx([10.0] * 10)
    assert [f["distance"] for _, _, f in odo] == pytest.approx(list(range(10)))
    plain = _csv(tmp_path, _rows10())
    assert csv2bag.main([str(plain), "--out", str(tmp_path / "c"), *ARGS,
                         "--delimiter", ";"]) == 2
    assert "separated by ';'" in capsys.readouterr().err


def test_a_stated_decimal_comma_is_never_taken_for_the_separator():
    """Lines that split into as many cells at the comma as at the semicolon (a column name
    with a comma, one decimal comma per row): found alone the separator could be either; with
    the decimal mark stated as ``,`` the comma is the numbers' and the separator is ``;``."""
    lines = ["zeit_s;weg, m", "100,5;12", "100,6;13", "100,7;14"]
    assert csv2bag._dialect(lines, csv2bag.Mapping(decimal=","))[:2] == (";", ",")
    assert csv2bag._dialect(lines, csv2bag.Mapping())[0] == ","  # undecidable: the first kind


def test_epoch_milliseconds_without_a_unit_are_refused_with_the_unit(tmp_path, capsys):
    log = tmp_path / "ms.csv"
    log.write_text("time,speed,distance\n" + "".join(
        f"{1732521600000 + 100 * i},10.0,{i}\n" for i in range(4)))
    assert csv2bag.main([str(log), "--out", str(tmp_path / "bag")]) == 2
    assert "Unix time in ms? --unit time=ms" in capsys.readouterr().err
    assert csv2bag.main([str(log), "--out", str(tmp_path / "bag"), "--unit", "time=ms"]) == 0
    odo = read_bag(tmp_path / "bag").topics["odometer"]
    assert [s for _, s, _ in odo] == pytest.approx([1732521600.0 + 0.1 * i for i in range(4)])


@pytest.mark.parametrize("text, what", [("columns: [t_ref, v_kmh, odo_m]", "columns must map"),
                                        ("units: km/h", "units must map"),
                                        ("columns:\n  time: t\ncolumns:\n  speed: v",
                                         "given twice")])
def test_a_map_file_of_the_wrong_shape_is_refused_by_name(tmp_path, capsys, text, what):
    log = _csv(tmp_path, ["100.0,5000,36.0,0.0,,50.0,0.0"])
    (tmp_path / "map.yaml").write_text(text + "\n")
    assert csv2bag.main([str(log), "--out", str(tmp_path / "bag"),
                         "--map", str(tmp_path / "map.yaml")]) == 2
    assert what in capsys.readouterr().err


def _plain(tmp_path, text: str, name: str = "p.csv") -> Path:
    p = tmp_path / name
    p.write_text(text)
    return p


def test_units_written_in_the_header_or_a_units_row_are_read(tmp_path, capsys):
    rows = "".join(f"{100 + i}.0,36,{0.01 * i:.2f}\n" for i in range(4))
    for i, head in enumerate(("time,speed [km/h],distance (km)\n",
                              "time,speed,distance\ns,km/h,km\n")):
        out = tmp_path / f"bag{i}"
        assert csv2bag.main([str(_plain(tmp_path, head + rows)), "--out", str(out)]) == 0
        assert "speed km/h, distance km" in capsys.readouterr().out
        odo = read_bag(out).topics["odometer"]
        assert [f["speed"] for _, _, f in odo] == pytest.approx([10.0] * 4)
        assert [f["distance"] for _, _, f in odo] == pytest.approx([0, 10, 20, 30])
    # a mapping used for two files: the first's header units are not the second's
    m = csv2bag.Mapping()
    csv2bag.convert(_plain(tmp_path, "time,speed [km/h],distance\n" + rows, "e.csv"),
                    tmp_path / "e", m)
    csv2bag.convert(_plain(tmp_path, "time,speed,distance\n" + rows, "f.csv"), tmp_path / "f", m)
    assert m.units == {} and [f["speed"] for _, _, f in
                              read_bag(tmp_path / "f").topics["odometer"]] == [36.0] * 4
    log = _plain(tmp_path, "time,speed [km/h],distance\n" + rows)
    assert csv2bag.main([str(log), "--out", str(tmp_path / "c"), "--unit", "speed=m/s"]) == 2
    assert "the file gives speed in km/h, the mapping says m/s" in capsys.readouterr().err
    log = _plain(tmp_path, "time,speed [mph],distance\n" + rows)
    assert csv2bag.main([str(log), "--out", str(tmp_path / "d")]) == 2
    assert "'mph': use one of m/s, km/h" in capsys.readouterr().err


def test_rows_that_would_be_misread_are_bad_rows(tmp_path, capsys):
    head = "time,speed,distance,seq\n"
    rows = [f"{100 + i}.0,10.0,{i},{1000 + 2 * i}" for i in range(6)]
    bad = {"counter": rows[:3] + ["103.0,10.0,3,"] + rows[4:],
           "ragged": rows[:3] + ["103.0,12,5,3,1006"] + rows[4:]}
    for what, rs in bad.items():
        log = _plain(tmp_path, head + "".join(r + "\n" for r in rs), f"{what}.csv")
        assert csv2bag.main([str(log), "--out", str(tmp_path / what),
                             "--column", "sample=seq"]) == 2
        err = capsys.readouterr().err
        assert "line 5" in err and ("no sample counter" in err if what == "counter"
                                    else "5 cells under a header of 4" in err)
    # a decimal-comma file (found from its first 50 lines) writing 1002 m as 1.002 from line 52
    log = _plain(tmp_path, "time;speed;distance\n" + "".join(
        f"{100 + i};10,5;{950 + i if i < 50 else f'1.{i - 50:03d}'}\n" for i in range(60)))
    assert csv2bag.main([str(log), "--out", str(tmp_path / "th")]) == 2
    assert "line 52: distance '1.000' has a '.' in a file whose decimal mark is ','" \
        in capsys.readouterr().err


def test_rows_with_a_time_only_are_samples_that_did_not_come(tmp_path, capsys):
    text = "time,speed,distance\n" + "".join(
        f"{100 + i}.0,,\n" if i % 10 == 5 else f"{100 + i}.0,10.0,{10 * i}\n"
        for i in range(40))
    assert csv2bag.main([str(_plain(tmp_path, text)), "--out", str(tmp_path / "bag")]) == 0
    out = capsys.readouterr().out
    assert "4 rows hold a time and nothing else" in out
    assert "36 of 40 in the log, 4 lost" in out


def test_a_train_clock_restarted_mid_log_is_numbered_on_not_counted_lost(tmp_path, capsys):
    text = "time,tt,speed,distance\n" + "".join(
        f"{1000 + 0.1 * i:.1f},{3600 + 0.1 * i if i < 50 else 0.1 * (i - 50):.1f},10,{i}\n"
        for i in range(100) if i != 70)  # one sample lost after the reboot
    log = _plain(tmp_path, text)
    assert csv2bag.main([str(log), "--out", str(tmp_path / "bag"),
                         "--column", "train_time=tt"]) == 0
    out = capsys.readouterr().out
    assert "99 of 100 in the log, 1 lost (1.0 %) in 1 gaps" in out
    assert "the train clock restarted 1 time (at line 52" in out
    seq = [f["seq"] for _, _, f in read_bag(tmp_path / "bag").topics["odometer"]]
    assert seq == [*range(1, 71), *range(72, 101)]


def test_what_a_spreadsheet_writes_around_the_table_is_read(tmp_path, capsys):
    body = "time\tspeed\tdistance\r\n1.0\t1.0\t1.0\r\n1.1\t1.0\t2.0\r\n"
    (tmp_path / "u16.csv").write_bytes(body.encode("utf-16"))  # "Unicode text": BOM + UTF-16
    assert csv2bag.main([str(tmp_path / "u16.csv"), "--out", str(tmp_path / "a")]) == 0
    assert "read as UTF-16 (its byte-order mark)" in capsys.readouterr().out
    log = _plain(tmp_path, "# recorder XY v2\nsep=;\ntime;speed;distance\n1,0;1,0;1,0\n"
                           "1,1;1,0;x\n")
    assert csv2bag.main([str(log), "--out", str(tmp_path / "b")]) == 2
    assert "line 5: distance 'x' is not a number" in capsys.readouterr().err  # lines as in file
    log = _plain(tmp_path, "time,speed,distance\n" + "".join(
        f"{i}.0,10.0,{i}\n" for i in range(60)) + "60.0,1,5,60\n", "late_comma.csv")
    assert csv2bag.main([str(log), "--out", str(tmp_path / "c")]) == 2
    log = _plain(tmp_path, "time;speed;distance\n" + "".join(
        f"{i};10;{i}\n" for i in range(60)) + "60;1,5;60\n", "late_comma2.csv")
    assert csv2bag.main([str(log), "--out", str(tmp_path / "c")]) == 2
    assert "speed '1,5' is not a number (a decimal comma? state --decimal ," \
        in capsys.readouterr().err
    log = _plain(tmp_path, "time,speed,distance,speed\n1,1,1,2\n", "twice.csv")
    assert csv2bag.main([str(log), "--out", str(tmp_path / "d")]) == 2
    assert "the header names 'speed' twice" in capsys.readouterr().err


def test_a_command_above_100_percent_is_a_bad_row(tmp_path, capsys):
    log = _csv(tmp_path, ["100.0,5000,36.0,0.0,,50.0,0.0", "100.1,5100,36.0,1.0,,150.0,0.0"])
    assert csv2bag.main([str(log), "--out", str(tmp_path / "bag"), *ARGS]) == 2
    assert "line 3: traction 150 % is above 100 % of traction_max" in capsys.readouterr().err
