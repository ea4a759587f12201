"""`csv2bag`: a data recorder's CSV log into a measured-data bag (docs/interfaces.md).

    csv2bag LOG.csv --out BAG [--map MAP.yaml] [--line line.yaml] [--column KEY=NAME ...]
            [--unit KEY=UNIT ...] [--skip-bad-rows]

One CSV row per odometer sample. The columns (KEY: what it holds; rename with --column or the
map's ``columns``, units with --unit or the map's ``units``):

  time        the reference clock (the recorder's), required: the bag's log time of every
              message and the stamp of ``control``                     units: s | ms
  train_time  the train's own clock, stamping ``odometer`` and ``balise`` (the sampling time
              on the train; any epoch). Optional: without it the train clock is the reference
                                                                        units: s | ms
  speed       axle speed, required                                     units: m/s | km/h
  distance    distance counted since the run started, required         units: m | km
  balise      balise id, on the row of each balise passage (empty otherwise); its surveyed
              position comes from --line (``balises``) or from a ``balise_position`` column (m)
  traction    traction command, >= 0        units: m/s^2 | percent (of ``traction_max``)
  braking     braking command magnitude, >= 0   units: m/s^2 | percent (of ``braking_max``)
              ``control``'s target_acceleration = traction - braking (one per row, when
              either column is mapped)

The map file (YAML, every key optional; options override it):

  columns: {time: t_ref, train_time: t_train, speed: v_kmh, ...}
  units: {time: s, speed: km/h, traction: percent, braking: percent, ...}
  traction_max: 1.0     # m/s^2 at 100 % traction
  braking_max: 1.2      # m/s^2 at 100 % braking
  speed_std: 0.1        # m/s, the odometer's stated speed noise (speed_variance = std^2)
  balise_std: 1.0       # m, the balise position's standard deviation
  delimiter: ","

The odometer's ``seq`` is the row's sample number (1 for the first data row), so a skipped row
shows as a lost sample, as a dropout would. A bad row (not a number, missing value, not finite,
time not increasing, negative time or command, unknown balise) stops the conversion with its
line number (exit 2), or with --skip-bad-rows is left out and counted by reason.

Exit status: 0 the bag was written; 2 unusable input (one line on stderr).
"""

from __future__ import annotations

import argparse
import csv
import math
import shutil
import sys
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import yaml
from train_core.bagio import BagError, BagWriter
from train_core.config import ConfigError
from train_core.model import load_line

KEYS = ("time", "train_time", "speed", "distance", "balise", "balise_position", "traction",
        "braking")
REQUIRED = ("time", "speed", "distance")
UNITS = {  # key: {unit: factor to SI}
    "time": {"s": 1.0, "ms": 1e-3},
    "train_time": {"s": 1.0, "ms": 1e-3},
    "speed": {"m/s": 1.0, "km/h": 1 / 3.6},
    "distance": {"m": 1.0, "km": 1000.0},
    "balise_position": {"m": 1.0, "km": 1000.0},
    "traction": {"m/s^2": 1.0, "percent": None},
    "braking": {"m/s^2": 1.0, "percent": None},
}


class InputError(ValueError):
    """Unusable input: one line, exit code 2."""


@dataclass
class Mapping:
    """Where each quantity is in the CSV and in what unit."""

    columns: dict = field(default_factory=dict)  # KEY -> CSV column name
    units: dict = field(default_factory=dict)  # KEY -> unit name (UNITS)
    traction_max: float | None = None  # m/s^2 at 100 % traction
    braking_max: float | None = None  # m/s^2 at 100 % braking
    speed_std: float = 0.1  # m/s, odometer speed noise (1 sigma)
    balise_std: float = 1.0  # m, balise position noise (1 sigma)
    delimiter: str = ","

    def factor(self, key: str) -> float:
        unit = self.units.get(key, next(iter(UNITS[key])))
        if unit not in UNITS[key]:
            raise InputError(f"unit {unit!r} for {key}: use one of {', '.join(UNITS[key])}")
        f = UNITS[key][unit]
        if f is None:  # percent of the command's maximum
            top = self.traction_max if key == "traction" else self.braking_max
            if top is None or not (math.isfinite(top) and top > 0):
                raise InputError(f"{key} in percent needs {key}_max (m/s^2 at 100 %) > 0")
            f = top / 100.0
        return f


def _pairs(items, what: str) -> dict:
    out = {}
    for it in items or []:
        k, sep, v = it.partition("=")
        if not sep or not v:
            raise InputError(f"--{what} {it!r}: write KEY=VALUE")
        out[k.strip()] = v.strip()
    return out


def load_mapping(path: str | None, columns=(), units=()) -> Mapping:
    """The map file (if any) with the command line's --column/--unit on top."""
    d: dict = {}
    if path:
        try:
            d = yaml.safe_load(Path(path).read_text()) or {}
        except (OSError, yaml.YAMLError) as e:
            raise InputError(f"cannot read the map {path}: {str(e).splitlines()[0]}") from None
        if not isinstance(d, dict):
            raise InputError(f"{path}: a mapping of columns, units, ... expected")
        unknown = set(d) - {"columns", "units", "traction_max", "braking_max", "speed_std",
                            "balise_std", "delimiter"}
        if unknown:
            raise InputError(f"{path}: unknown keys {sorted(unknown)}")
    m = Mapping(columns=dict(d.get("columns") or {}), units=dict(d.get("units") or {}))
    m.columns.update(_pairs(columns, "column"))
    m.units.update(_pairs(units, "unit"))
    for k in list(m.columns) + list(m.units):
        if k not in KEYS:
            raise InputError(f"unknown quantity {k!r}: use one of {', '.join(KEYS)}")
    for k in ("traction_max", "braking_max", "speed_std", "balise_std"):
        if d.get(k) is not None:
            try:
                setattr(m, k, float(d[k]))
            except (TypeError, ValueError):
                raise InputError(f"{path}: {k} must be a number, got {d[k]!r}") from None
    if not (math.isfinite(m.speed_std) and m.speed_std > 0 and math.isfinite(m.balise_std)
            and m.balise_std > 0):
        raise InputError("speed_std and balise_std must be > 0")
    m.delimiter = str(d.get("delimiter", ","))
    for k in m.units:
        m.factor(k)  # unknown units and missing maxima fail before any row is read
    return m


class BadRow(ValueError):
    def __init__(self, reason: str, detail: str):
        super().__init__(detail)
        self.reason = reason


@dataclass
class Result:
    rows: int = 0  # data rows read
    written: Counter = field(default_factory=Counter)  # topic -> messages
    skipped: Counter = field(default_factory=Counter)  # reason -> rows
    first_skipped: list = field(default_factory=list)  # "line N: why" of the first few


def convert(csv_path: str | Path, out: str | Path, mapping: Mapping, line=None,
            skip_bad_rows: bool = False, namespace: str = "/train") -> Result:
    """Write the bag ``out`` from the CSV (module docstring); raises InputError."""
    try:
        fh = open(csv_path, newline="")
    except OSError as e:
        raise InputError(f"cannot read {csv_path}: {e.strerror}") from None
    with fh:
        reader = csv.reader(fh, delimiter=mapping.delimiter)
        header = next(reader, None)
        if not header:
            raise InputError(f"{csv_path} is empty: a header row of column names is expected")
        header = [h.strip() for h in header]
        col = {}
        for key in KEYS:
            name = mapping.columns.get(key, key)
            if name in header:
                col[key] = header.index(name)
            elif key in mapping.columns or key in REQUIRED:
                raise InputError(f"{csv_path}: no column {name!r} for {key} (columns: "
                                 f"{', '.join(header)}; map it with --column {key}=NAME)")
        if "balise" in col and "balise_position" not in col and line is None:
            raise InputError("balise passages need their positions: give --line line.yaml or "
                             "a balise_position column")
        fac = {k: mapping.factor(k) for k in col if k in UNITS}
        commands = "traction" in col or "braking" in col
        res = Result()
        if Path(out).exists():
            raise InputError(f"{out} exists already: choose a new bag directory")
        try:
            writer = BagWriter(out, namespace=namespace)
        except BagError as e:
            raise InputError(str(e)) from None
        try:
            with writer:
                _rows(reader, col, fac, line, mapping, skip_bad_rows, commands, writer, res,
                      csv_path)
        except (InputError, csv.Error) as e:
            shutil.rmtree(out, ignore_errors=True)  # no half-written bag is left behind
            if isinstance(e, csv.Error):
                raise InputError(f"{csv_path}: not a readable CSV ({e})") from None
            raise
    if res.written["odometer"] == 0:
        shutil.rmtree(out, ignore_errors=True)
        raise InputError(f"{csv_path}: no usable data row")
    return res


def _rows(reader, col, fac, line, mapping, skip_bad_rows, commands, writer, res, csv_path):
    last_t = last_tt = -math.inf
    n_bal = 0
    for lineno, row in enumerate(reader, start=2):
        if not row or all(not c.strip() for c in row):
            continue
        res.rows += 1
        seq = res.rows
        try:
            v = _row(row, col, fac, line, lineno)
            if v["time"] <= last_t:
                raise BadRow("out_of_order", f"time {v['time']} s is not after the "
                             f"previous row's {last_t} s")
            if v["train_time"] <= last_tt:
                raise BadRow("out_of_order", f"train_time {v['train_time']} s is not "
                             f"after the previous row's {last_tt} s")
        except BadRow as e:
            if not skip_bad_rows:
                raise InputError(f"{csv_path} line {lineno}: {e} (use --skip-bad-rows "
                                 "to leave such rows out)") from None
            res.skipped[e.reason] += 1
            if len(res.first_skipped) < 5:
                res.first_skipped.append(f"line {lineno}: {e}")
            continue
        last_t, last_tt = v["time"], v["train_time"]
        t_ns = int(round(v["time"] * 1e9))
        writer.write("odometer", v["train_time"], {
            "seq": seq, "distance": v["distance"], "speed": v["speed"],
            "speed_variance": mapping.speed_std ** 2}, t_ns=t_ns)
        res.written["odometer"] += 1
        if v.get("balise_id") is not None:
            n_bal += 1
            writer.write("balise", v["train_time"], {
                "seq": n_bal, "balise_id": v["balise_id"],
                "position": v["balise_position"],
                "position_variance": mapping.balise_std ** 2}, t_ns=t_ns)
            res.written["balise"] += 1
        if commands:
            writer.write("control", v["time"], {
                "target_acceleration": v.get("traction", 0.0) - v.get("braking", 0.0)},
                t_ns=t_ns)
            res.written["control"] += 1


def _number(row, col, key, lineno) -> float | None:
    i = col.get(key)
    if i is None:
        return None
    text = row[i].strip() if i < len(row) else ""
    if not text:
        return None
    try:
        x = float(text)
    except ValueError:
        raise BadRow("not_a_number", f"{key} {text!r} is not a number") from None
    if not math.isfinite(x):
        raise BadRow("non_finite", f"{key} is {text}")
    return x


def _row(row, col, fac, line, lineno) -> dict:
    v: dict = {}
    for key in ("time", "train_time", "speed", "distance", "traction", "braking",
                "balise_position"):
        x = _number(row, col, key, lineno)
        if x is None:
            if key in REQUIRED:
                raise BadRow("missing", f"no {key} value")
            continue
        v[key] = x * fac[key]
    v.setdefault("train_time", v["time"])
    for key in ("time", "train_time", "traction", "braking"):
        if v.get(key, 0.0) < 0:
            raise BadRow("negative", f"{key} {v[key]:g} < 0 (clocks count from 0 or an "
                         "epoch; braking is a magnitude)")
    bid = _number(row, col, "balise", lineno)
    if bid is not None:
        if bid != int(bid) or bid < 0:
            raise BadRow("not_a_number", f"balise id {bid:g} is not a whole number >= 0")
        v["balise_id"] = int(bid)
        if "balise_position" not in v:
            b = line.balise_by_id(int(bid)) if line is not None else None
            if b is None:
                raise BadRow("unknown_balise", f"balise {int(bid)} is not in the line file")
            v["balise_position"] = float(b.position)
    return v


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="csv2bag", description=__doc__.splitlines()[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter,
                                epilog="\n".join(__doc__.splitlines()[2:]))
    p.add_argument("csv", help="the recorder's CSV log (a header row, one row per sample)")
    p.add_argument("--out", required=True, help="the bag directory to write (must not exist)")
    p.add_argument("--map", help="YAML: columns, units, traction_max, braking_max, ...")
    p.add_argument("--line", help="line.yaml: balise positions by id")
    p.add_argument("--column", action="append", metavar="KEY=NAME",
                   help="CSV column of a quantity, e.g. speed=v_kmh (repeatable)")
    p.add_argument("--unit", action="append", metavar="KEY=UNIT",
                   help="unit of a quantity, e.g. speed=km/h (repeatable)")
    p.add_argument("--skip-bad-rows", action="store_true",
                   help="leave bad rows out and count them (default: stop at the first)")
    p.add_argument("--namespace", default="/train", help="topic namespace (default /train)")
    args = p.parse_args(argv)
    try:
        mapping = load_mapping(args.map, args.column, args.unit)
        line = load_line(args.line) if args.line else None
        res = convert(args.csv, args.out, mapping, line, args.skip_bad_rows, args.namespace)
    except (InputError, ConfigError, BagError) as e:
        print(f"csv2bag: {e}", file=sys.stderr)
        return 2
    counts = ", ".join(f"{k} {n}" for k, n in sorted(res.written.items()))
    print(f"wrote {args.out}: {res.rows} rows -> {counts}")
    if res.skipped:
        print(f"skipped {sum(res.skipped.values())} bad rows: "
              + ", ".join(f"{k} {n}" for k, n in sorted(res.skipped.items())))
        for s in res.first_skipped:
            print(f"  {s}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
