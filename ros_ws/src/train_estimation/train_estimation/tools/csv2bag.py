"""`csv2bag`: a data recorder's CSV log into a measured-data bag (docs/interfaces.md).

    csv2bag LOG.csv --out BAG [--map MAP.yaml] [--line line.yaml] [--column KEY=NAME ...]
            [--unit KEY=UNIT ...] [--delimiter D] [--decimal . | ,] [--encoding E] [--sort]
            [--skip-bad-rows] [--max-skipped N|P%]

One CSV row per event: an odometer sample (speed and distance), a balise passage, a command,
or several of them on one row. The columns (KEY: what it holds; rename with --column or the
map's ``columns``, units with --unit or the map's ``units``):

  time        the reference clock (the recorder's), required: the bag's log time of every
              message and the stamp of ``control``
                                      units: s | ms | us | ns (numbers), or text: ISO 8601
                                      date-times
                                      (2026-12-01T23:59:59.900Z; no zone = UTC) or times of
                                      day (23:59:59.900)
  train_time  the train's own clock, stamping ``odometer`` and ``balise`` (the sampling time
              on the train; any epoch). Optional: without it the train clock is the reference
                                                          units: as time
  sample      the odometer's sample counter (+1 per sample on the train), where the log has
              one: the odometer's ``seq``. Without it the samples are numbered from the train
              clock's period (below)
  speed       axle speed                                               units: m/s | km/h
  distance    distance counted since the run started                   units: m | km
              (speed and distance are required columns; a row with both empty is a row of
              commands or balises only)
  balise      balise id, on the row of each balise passage (empty otherwise); its surveyed
              position comes from --line (``balises``) or from a ``balise_position`` column (m)
  traction    traction command, >= 0        units: m/s^2 | percent (of ``traction_max``)
  braking     braking command magnitude, >= 0   units: m/s^2 | percent (of ``braking_max``)
              a row with either gives one ``control`` message, target_acceleration =
              traction - braking (an empty one counts 0); a row with neither gives none

The map file (YAML, every key optional; options override it; extra keys are named in a
warning):

  columns: {time: t_ref, train_time: t_train, speed: v_kmh, ...}
  units: {time: s, speed: km/h, traction: percent, braking: percent, ...}
  traction_max: 1.0     # m/s^2 at 100 % traction
  braking_max: 1.2      # m/s^2 at 100 % braking
  speed_std: 0.1        # m/s, the odometer's stated speed noise (speed_variance = std^2)
  balise_std: 1.0       # m, the balise position's standard deviation
  delimiter: ";"        # the field separator (default: found from the file's first lines)
  decimal: ","          # the decimal mark of numbers (default: found from the file)
  encoding: cp1252      # the text's encoding (default utf-8, with or without a BOM)

The file's format. Spreadsheets and recorders write CSV in more than one way: the separator is a
comma, a semicolon (where the comma is the decimal mark), a tab or a bar, and numbers may be
written 0,36 instead of 0.36. Unless stated (the map or the options), the separator is the one
of ``, ; TAB |`` that splits the header into the most columns and the first data rows into as
many (never the comma where the decimal mark is stated as one), and the decimal mark is a comma
where the separator is not one and the first rows write their numbers with a comma and never
with a point; what was found is printed when it is not the plain form. Quoted cells, spaces
after the separator, Windows line ends and a UTF-8 byte-order mark (a spreadsheet's "CSV UTF-8")
are read as they are meant. Text that is not UTF-8 (an older Windows export) stops with the byte
where it failed: state its encoding.

Lost samples. The odometer's ``seq`` is the sample counter where the log has one. Otherwise the
train clock's sampling period is estimated from the odometer stamps (the median step, refined
over every step as a whole number of periods) and each sample is numbered by the periods since
the previous one, so a sample missing from the log (lost on the way, or a bad row left out)
shows as a lost sample, as a dropout would. How many were lost and where is printed.

Clocks. Times of day (text, or numbers under 86 400 s) that step back by more than 12 h have
crossed midnight: a day is added (printed). Rows must come in reference-time order (the train
clock's stamps need not: a link with jitter delivers samples out of order): a row earlier than
the one before stops the conversion unless --sort sorts the rows by the reference time (stable)
first.

Bad rows (not a number, missing value, not finite, out of order, negative time or command,
unknown balise) stop the conversion with their line number (exit 2), or with --skip-bad-rows
are left out and counted by reason, up to --max-skipped (default 1 % of the data rows): more
is an error, no bag is written (a mass skip means the mapping or the format is wrong).

Exit status: 0 the bag was written; 2 unusable input (one line on stderr).
"""

from __future__ import annotations

import argparse
import codecs
import csv
import dataclasses
import itertools
import math
import re
import shutil
import sys
from collections import Counter
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
from train_core.bagio import BagError, BagWriter
from train_core.config import ConfigError, ConfigWarning, check_keys, load_yaml
from train_core.model import load_line

from train_estimation.core.offline.measured import counter_gaps, counter_runs
from train_estimation.tools.common import cannot_write_there, pipe_safe

KEYS = ("time", "train_time", "sample", "speed", "distance", "balise", "balise_position",
        "traction", "braking")
REQUIRED = ("time", "speed", "distance")
NUMERIC = ("sample", "speed", "distance", "balise", "balise_position", "traction", "braking")
UNITS = {  # key: {unit: factor to SI}
    "time": {"s": 1.0, "ms": 1e-3, "us": 1e-6, "ns": 1e-9},
    "train_time": {"s": 1.0, "ms": 1e-3, "us": 1e-6, "ns": 1e-9},
    "speed": {"m/s": 1.0, "km/h": 1 / 3.6},
    "distance": {"m": 1.0, "km": 1000.0},
    "balise_position": {"m": 1.0, "km": 1000.0},
    "traction": {"m/s^2": 1.0, "percent": None},
    "braking": {"m/s^2": 1.0, "percent": None},
}
# a unit as a recorder or a spreadsheet writes it -> its name in UNITS
UNIT_ALIASES = {"sec": "s", "secs": "s", "kmh": "km/h", "kph": "km/h", "km/hr": "km/h",
                "mps": "m/s", "m/s2": "m/s^2", "m/s\u00b2": "m/s^2", "%": "percent",
                "\u00b5s": "us"}
_HEADER_UNIT = re.compile(r"^(.*?)\s*[\[(]\s*([^\])]+?)\s*[\])]$")  # "speed [km/h]"
MAP_KEYS = {"columns": "mapping", "units": "mapping", "traction_max": "number",
            "braking_max": "number", "speed_std": "number", "balise_std": "number",
            "delimiter": "string", "decimal": "string", "encoding": "string"}
DAY = 86400.0  # s
TIME_MAX = 2.0 ** 31  # s: a stamp's int32 seconds (builtin_interfaces/Time): 2038-01-19
SEQ_MAX = 2 ** 32 - 1  # OdometerReading.seq is a uint32
MAX_SKIPPED = "1%"


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
    delimiter: str | None = None  # field separator; None: found from the file (_dialect)
    decimal: str | None = None  # "." or ","; None: found from the file (_dialect)
    encoding: str = "utf-8"  # the text's encoding (a UTF-8 byte-order mark is skipped)

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


def load_mapping(path: str | None, columns=(), units=(), delimiter: str | None = None,
                 decimal: str | None = None, encoding: str | None = None) -> Mapping:
    """The map file (if any) with the command line's --column/--unit (and the format's
    options) on top."""
    d: dict = {}
    if path:
        try:  # the rules of every YAML the project reads (UTF-8, no key given twice, ...)
            empty = not Path(path).read_text(errors="replace").strip()
            d = {} if empty else load_yaml(path)
            # extra keys: the rule of every reader (train_core.config.unknown_key)
            check_keys(d, MAP_KEYS, str(path))
        except OSError as e:
            raise InputError(f"cannot read the map {path}: {str(e).splitlines()[0]}") from None
        except ConfigError as e:
            raise InputError(str(e)) from None
        for key in ("columns", "units"):  # each {quantity: a column's name or a unit}
            v = d.get(key)
            if v is not None and not (isinstance(v, dict) and all(
                    isinstance(x, str | int | float) and not isinstance(x, bool)
                    for x in v.values())):
                raise InputError(f"{path}: {key} must map a quantity to a "
                                 f"{'column name' if key == 'columns' else 'unit'}, e.g. "
                                 f"{'speed: v_kmh' if key == 'columns' else 'speed: km/h'}; "
                                 f"got {v!r}")
    m = Mapping(columns={k: str(v) for k, v in (d.get("columns") or {}).items()},
                units={k: str(v) for k, v in (d.get("units") or {}).items()})
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
    delimiter = delimiter if delimiter is not None else d.get("delimiter")
    if delimiter is not None:
        m.delimiter = {"tab": "\t", "\\t": "\t"}.get(str(delimiter), str(delimiter))
        if len(m.delimiter) != 1 or m.delimiter in "\"\r\n" or m.delimiter.isalnum():
            raise InputError(f"delimiter {delimiter!r}: one character such as , ; | or tab")
    decimal = decimal if decimal is not None else d.get("decimal")
    if decimal is not None:
        m.decimal = str(decimal)
        if m.decimal not in (".", ","):
            raise InputError(f"decimal {decimal!r}: . or ,")
    if m.decimal == "," and m.delimiter == ",":
        raise InputError("decimal , needs another delimiter than , (e.g. ;)")
    encoding = encoding if encoding is not None else d.get("encoding")
    if encoding is not None:
        m.encoding = str(encoding)
        try:
            codecs.lookup(m.encoding)
        except LookupError:
            raise InputError(f"encoding {m.encoding!r} is not known (e.g. utf-8, cp1252, "
                             "latin-1)") from None
    for k in m.units:
        if k in UNITS:
            m.factor(k)  # unknown units and missing maxima fail before any row is read
        else:
            raise InputError(f"{k} has no unit (it is {'a count' if k == 'sample' else 'an id'})")
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
    numbering: str = ""  # "counter" (the log's sample column) or "period" (from the stamps)
    period: float = math.nan  # s, the train clock's sampling period (numbering "period")
    samples: int = 0  # odometer samples the numbering spans (first to last)
    lost: int = 0  # of them, missing from the log
    gaps: list = field(default_factory=list)  # (line, samples lost before it, s since the
    #                                           first sample on the train clock)
    rollovers: list = field(default_factory=list)  # (column key, line) of each midnight
    moved: int = 0  # rows --sort moved
    restarts: int = 0  # times the log's sample counter went back while the train clock ran on
    dialect: tuple = (",", ".", "")  # (delimiter, decimal, what was found rather than stated)
    file_units: dict = field(default_factory=dict)  # key -> unit the file wrote (header or row)
    time_only: int = 0  # rows with a time and nothing else (a recorder's row for a lost sample)
    clock_restarts: list = field(default_factory=list)  # lines where the train clock restarted
    encoding: str = ""  # the encoding found from the file's byte-order mark, if not stated
    preamble: int = 0  # lines before the header: comments (#) and a spreadsheet's sep= line


# ------------------------------------------------------------------------------------------------
# Cells
# ------------------------------------------------------------------------------------------------

_TOD = re.compile(r"^(\d{1,2}):(\d{2}):(\d{2}(?:\.\d*)?)$")


def _time_cell(text: str, key: str, factor: float) -> tuple[float, bool]:
    """(seconds, is a time of day) of a time cell: a number in the column's unit, an ISO 8601
    date-time (Unix seconds; no zone = UTC) or a time of day HH:MM:SS[.fff]."""
    try:
        x = float(text)
    except ValueError:
        pass
    else:
        if not math.isfinite(x):
            raise BadRow("non_finite", f"{key} is {text}")
        if abs(x * factor) >= TIME_MAX:
            # a whole column in another unit (a recorder's epoch milliseconds or nanoseconds),
            # not one bad row: stamps hold seconds up to 2038 only
            unit = next((u for u, f in UNITS[key].items() if f < factor and
                         abs(x * f) < TIME_MAX and abs(x * f) >= 1e8), None)
            raise InputError(f"{key} {text} is {x * factor:.4g} s, beyond what a stamp holds "
                             f"(2038)" + (f": Unix time in {unit}? --unit {key}={unit}"
                                          if unit else f": state its unit (--unit {key}=...)"))
        x *= factor
        return x, 0.0 <= x < DAY
    m = _TOD.match(text)
    if m:
        h, mi, s = int(m.group(1)), int(m.group(2)), float(m.group(3))
        if h < 24 and mi < 60 and s < 61:
            return h * 3600.0 + mi * 60.0 + s, True
    try:
        dt = datetime.fromisoformat(text.replace("Z", "+00:00").replace("z", "+00:00"))
    except ValueError:
        raise BadRow("not_a_number", f"{key} {text!r} is neither a number, an ISO 8601 "
                     "date-time nor a time of day HH:MM:SS") from None
    if dt.tzinfo is None:
        dt = dt.replace(tzinfo=timezone.utc)
    return dt.timestamp(), False


def _cell(row, col, key) -> str:
    i = col.get(key)
    if i is None or i >= len(row):
        return ""
    return row[i].strip()


def _number(row, col, key) -> float | None:
    text = _cell(row, col, key)
    if not text:
        return None
    try:
        x = float(text)
    except ValueError:
        hint = " (a decimal comma? state --decimal , where the file writes them)" \
            if _COMMA_NUMBER.match(text) else ""
        raise BadRow("not_a_number", f"{key} {text!r} is not a number{hint}") from None
    if not math.isfinite(x):
        raise BadRow("non_finite", f"{key} is {text}")
    return x


@dataclass
class _Row:
    line: int
    time: float  # s, reference clock (midnights added)
    train_time: float | None  # s, train clock (midnights added); None: not on this row
    values: dict  # speed, distance, sample, traction, braking, balise_id, balise_position


class _Clock:
    """A time column read in file order: times of day that step back by more than half a day
    have crossed midnight, and a day is added from there on."""

    def __init__(self, key: str, factor: float):
        self.key, self.factor = key, factor
        self.days = 0
        self.last = None  # the last time of day read (s, without the added days)
        self.rollovers: list[int] = []

    def read(self, text: str, line: int) -> float:
        x, of_day = _time_cell(text, self.key, self.factor)
        if not of_day:
            return x
        if self.last is not None and x < self.last - DAY / 2:
            self.days += 1
            self.rollovers.append(line)
        self.last = x
        return x + self.days * DAY


class _TimeOnly(Exception):
    """A row with a time and every other cell read empty: a recorder that writes a row per
    period whether or not a sample came (the lost ones empty). Left out and counted; the
    numbering finds the samples lost."""


def _parse(row, line, col, fac, lookup, clocks) -> _Row:
    text = _cell(row, col, "time")
    if not text:
        raise BadRow("missing", "no time value")
    t = clocks["time"].read(text, line)
    tt_text = _cell(row, col, "train_time") if "train_time" in col else text
    tt = (clocks["train_time"].read(tt_text, line) if "train_time" in col else t) \
        if tt_text else None
    v: dict = {}
    for key in ("speed", "distance", "traction", "braking", "balise_position"):
        x = _number(row, col, key)
        if x is not None:
            v[key] = x * fac[key]
    n = _number(row, col, "sample")
    if n is not None:
        if n != int(n) or not 0 <= n <= SEQ_MAX:
            raise BadRow("not_a_number", f"sample {n:g} is not a whole number in [0, 2^32)")
        v["sample"] = int(n)
    has_odo = "speed" in v or "distance" in v
    if has_odo and not ("speed" in v and "distance" in v):
        raise BadRow("missing", f"no {'distance' if 'speed' in v else 'speed'} value")
    if has_odo and "sample" in col and "sample" not in v:
        # the counter numbers the samples and counts the lost ones: a sample without it
        # cannot be placed (numbering the log by the stamps instead reported 0 % lost for 49 %)
        raise BadRow("missing", "no sample counter on an odometer row (the sample column "
                                "numbers the samples)")
    for key in ("time", "train_time"):
        val = t if key == "time" else tt
        if val is not None and val < 0:
            raise BadRow("negative", f"{key} {val:g} < 0 (clocks count from 0 or an epoch)")
    for key in ("traction", "braking"):
        if v.get(key, 0.0) < 0:
            raise BadRow("negative", f"{key} {v[key]:g} < 0 (braking is a magnitude)")
    bid = _number(row, col, "balise")
    if bid is not None:
        if bid != int(bid) or bid < 0:
            raise BadRow("not_a_number", f"balise id {bid:g} is not a whole number >= 0")
        v["balise_id"] = int(bid)
        if "balise_position" not in v:
            b = lookup(int(bid))
            if b is None:
                raise BadRow("unknown_balise", f"balise {int(bid)} is not in the line file")
            v["balise_position"] = float(b.position)
    commands = "traction" in v or "braking" in v
    if not (has_odo or commands or "balise_id" in v):
        if not any(_cell(row, col, k) for k in col if k not in ("time", "train_time")):
            raise _TimeOnly()  # a recorder's row for a sample it did not get: nothing to read
        raise BadRow("missing", "no speed, distance, command or balise on the row")
    if (has_odo or "balise_id" in v) and tt is None:
        raise BadRow("missing", "no train_time value (it stamps the odometer and balises)")
    return _Row(line, t, tt, v)


# ------------------------------------------------------------------------------------------------
# Sample numbers
# ------------------------------------------------------------------------------------------------

def sampling_period(stamps) -> float:
    """s, the train clock's sampling period from the stamps of the samples received (in any
    order): the
    median step (robust to gaps as long as fewer than half the steps span a loss), refined over
    every step as a whole number of those periods (so it is as exact as the whole log is
    long). NaN with fewer than two stamps or no forward step."""
    d = np.diff(np.sort(np.asarray(stamps, dtype=float)))  # in stamp order, not arrival's
    d = d[d > 0]  # a sample delivered twice is no step
    if d.size == 0:
        return math.nan
    p0 = float(np.median(d))
    k = np.maximum(1, np.rint(d / p0))
    return float(d.sum() / k.sum())


def number_samples(stamps, period: float) -> np.ndarray:
    """Sample numbers (1 for the earliest stamp) of samples stamped ``stamps`` (in any order:
    the arrival order of a link with jitter) on a clock sampling every ``period`` s: in stamp
    order each step counts the whole periods since the sample before, so rounding errors never
    accumulate across a long log, and a sample delivered twice (the same stamp) keeps its
    number (a duplicate, as the counter would say)."""
    stamps = np.asarray(stamps, dtype=float)
    if stamps.size == 0:
        return np.zeros(0, dtype=np.int64)
    order = np.argsort(stamps, kind="stable")
    if not (math.isfinite(period) and period > 0):
        k = (np.diff(stamps[order]) > 0).astype(np.int64)
    else:
        k = np.maximum(0, np.rint(np.diff(stamps[order]) / period)).astype(np.int64)
    seq = np.empty(stamps.size, dtype=np.int64)
    seq[order] = np.concatenate([[1], 1 + np.cumsum(k)])
    return seq


# ------------------------------------------------------------------------------------------------
# The conversion
# ------------------------------------------------------------------------------------------------

def max_skipped_rows(spec: str, rows: int) -> int:
    """Rows that --max-skipped allows: "N" rows or "P%" of ``rows`` (rounded up)."""
    s = str(spec).strip()
    try:
        if s.endswith("%"):
            p = float(s[:-1])
            if not (math.isfinite(p) and 0 <= p <= 100):
                raise ValueError
            return int(math.ceil(p / 100.0 * rows))
        n = int(s)
        if n < 0:
            raise ValueError
        return n
    except ValueError:
        raise InputError(f"--max-skipped {spec!r}: a number of rows (10) or a percentage of "
                         "the data rows (1%)") from None


def convert(csv_path: str | Path, out: str | Path, mapping: Mapping, line=None,
            skip_bad_rows: bool = False, namespace: str = "/train", sort: bool = False,
            max_skipped: str = MAX_SKIPPED) -> Result:
    """Write the bag ``out`` from the CSV (module docstring); raises InputError."""
    if Path(out).exists():
        raise InputError(f"{out} exists already: choose a new bag directory")
    res = Result()
    rows = _read(csv_path, mapping, line, skip_bad_rows, sort, res)
    allowed = max_skipped_rows(max_skipped, res.rows)
    n_skipped = sum(res.skipped.values())
    if n_skipped > allowed:
        reasons = ", ".join(f"{k} {n}" for k, n in res.skipped.most_common())
        first = f" (first: {res.first_skipped[0]})" if res.first_skipped else ""
        raise InputError(f"{csv_path}: {n_skipped} of {res.rows} rows would be skipped "
                         f"({reasons}){first}, more than --max-skipped {max_skipped} "
                         f"({allowed} rows): check the columns and units (--column, --unit, "
                         "--map); raise --max-skipped only if so many rows are truly bad")
    odo = [r for r in rows if "speed" in r.values]
    if not odo:
        raise InputError(f"{csv_path}: no usable odometer row (speed and distance)")
    _number_odometer(odo, res)
    try:
        writer = BagWriter(out, namespace=namespace)
    except BagError as e:
        raise InputError(str(e)) from None
    except OSError as e:  # a read-only place, a file in the way
        raise InputError(cannot_write_there(out, e)) from None
    try:
        with writer:
            _write(rows, mapping, writer, res)
    except BaseException:
        shutil.rmtree(out, ignore_errors=True)  # no half-written bag is left behind
        raise
    return res


DELIMITERS = (",", ";", "\t", "|")
DIALECT_LINES = 50  # the first lines that the separator and the decimal mark are found from
_COMMA_NUMBER = re.compile(r"^[+-]?\d+,\d+$")
_SEP_LINE = re.compile(r'^\s*"?sep=(.)"?\s*$')  # a spreadsheet's first line: "sep=;"
_POINT_NUMBER = re.compile(r"^[+-]?\d*\.\d+$")


def _dialect(lines: list[str], mapping: Mapping) -> tuple[str, str, str]:
    """(delimiter, decimal mark, what was found rather than stated) of a file whose first lines
    are ``lines`` (module doc, "The file's format")."""
    found = []
    delim = mapping.delimiter
    if delim is None:
        best = None
        # a stated decimal comma cannot also separate the fields (load_mapping refuses both)
        for d in (d for d in DELIMITERS if not (d == "," and mapping.decimal == ",")):
            rows = [r for r in csv.reader(lines, delimiter=d, skipinitialspace=True) if r]
            if not rows or len(rows[0]) < 2:
                continue
            score = (sum(len(r) == len(rows[0]) for r in rows[1:]), len(rows[0]))
            if best is None or score > best[0]:
                best = (score, d)
        delim = best[1] if best else ","
        found.append("delimiter")
    dec = mapping.decimal
    if dec is None:
        cells = [c.strip() for r in csv.reader(lines[1:], delimiter=delim) for c in r]
        dec = "," if delim != "," and any(_COMMA_NUMBER.match(c) for c in cells) and \
            not any(_POINT_NUMBER.match(c) for c in cells) else "."
        found.append("decimal")
    return delim, dec, " and ".join(found)


def _split_unit(header: str) -> tuple[str, str | None]:
    """A column name and the unit written in it: ``speed [km/h]`` or ``speed (km/h)``."""
    m = _HEADER_UNIT.match(header)
    return (m.group(1), m.group(2)) if m and m.group(1) else (header, None)


def _unit_name(text: str) -> str:
    return UNIT_ALIASES.get(text.strip().lower(), text.strip())


def _is_units_row(row: list, col: dict) -> bool:
    """Whether ``row``, the first under the header, is a row of units: no cell is a number and
    a column read holds a unit of its quantity (``s,km/h,m``)."""
    cells = [c.strip() for c in row]
    for c in cells:
        try:
            float(c.replace(",", "."))
            return False
        except ValueError:
            pass
    return any(k in UNITS and i < len(cells) and _unit_name(cells[i]) in UNITS[k]
               for k, i in col.items())


def _written_units(written: dict, mapping: Mapping, csv_path) -> dict:
    """Take the units the file writes (in its header or a units row) where none is stated;
    refuse one the file contradicts or one this tool does not know: a km/h column read as m/s
    would be 3.6 times too fast without a word. Returns the units taken from the file."""
    taken = {}
    for key, text in written.items():
        if not text or key not in UNITS:
            continue
        unit = _unit_name(text)
        stated = mapping.units.get(key)
        if unit not in UNITS[key] and stated is not None:
            continue  # a word this tool does not know, which the mapping says what it means
        if unit not in UNITS[key]:
            raise InputError(f"{csv_path}: the file gives {key} in {text!r}: use one of "
                             f"{', '.join(UNITS[key])} (state it with --unit {key}=UNIT if "
                             f"the file's word means one of them)")
        if stated is not None and stated != unit:
            raise InputError(f"{csv_path}: the file gives {key} in {unit}, the mapping says "
                             f"{stated}: remove one")
        mapping.units[key] = taken[key] = unit
    return taken


def _read(csv_path, mapping, line, skip_bad_rows, sort, res) -> list[_Row]:
    """The CSV's usable rows in time order (sorted if asked); bad rows raise or are counted."""
    enc = "utf-8-sig" if codecs.lookup(mapping.encoding).name == "utf-8" else mapping.encoding
    try:
        with open(csv_path, "rb") as raw:
            bom = raw.read(2)
        if enc == "utf-8-sig" and bom in (codecs.BOM_UTF16_LE, codecs.BOM_UTF16_BE):
            # a spreadsheet's "Unicode text": UTF-16, which its byte-order mark says
            enc = res.encoding = "utf-16"
        fh = open(csv_path, newline="", encoding=enc)
    except OSError as e:
        raise InputError(f"cannot read {csv_path}: {e.strerror}") from None
    try:
        with fh:
            return _read_rows(fh, csv_path, mapping, line, skip_bad_rows, sort, res)
    except UnicodeDecodeError as e:
        raise InputError(f"{csv_path}: not {mapping.encoding} text ({e.reason} at byte "
                         f"{e.start} of a line): state the file's encoding, e.g. --encoding "
                         "cp1252 (an older Windows export) or latin-1") from None


def _read_rows(fh, csv_path, mapping, line, skip_bad_rows, sort, res) -> list[_Row]:
    # this file's own copy: the units its header states (_written_units) are not the next
    # file's, converted with the same mapping
    mapping = dataclasses.replace(mapping, units=dict(mapping.units))
    head = [ln for ln in (fh.readline() for _ in range(DIALECT_LINES)) if ln]
    # lines before the header: a recorder's comments (#) and a spreadsheet's "sep=;" line,
    # which states the separator
    pre, sep = 0, None
    while pre < len(head) and (head[pre].lstrip().startswith("#") or _SEP_LINE.match(head[pre])):
        m = _SEP_LINE.match(head[pre])
        sep = m.group(1) if m else sep
        pre += 1
    res.preamble = pre
    fh.seek(0)
    for _ in range(pre):
        fh.readline()
    if sep is not None and mapping.delimiter is None:
        mapping = dataclasses.replace(mapping, delimiter=sep)
    delim, dec, found = _dialect(head[pre:], mapping)
    res.dialect = (delim, dec, found)
    with_comma = dec == ","  # 0,36: every comma of a cell is its decimal mark
    reader = csv.reader(fh, delimiter=delim, skipinitialspace=True)
    try:
        header = next(reader, None)
        if not header:
            raise InputError(f"{csv_path} is empty: a header row of column names is "
                             "expected")
        header = [h.strip() for h in header]
        col = {}
        for key in KEYS:
            name = mapping.columns.get(key, key)
            if header.count(name) > 1 or name not in header and \
                    [_split_unit(h)[0] for h in header].count(name) > 1:
                raise InputError(f"{csv_path}: the header names {name!r} twice (columns "
                                 f"{', '.join(header)}): which one is {key} is not "
                                 f"known; rename one in the file")
            if name in header:
                col[key] = header.index(name)
            elif name in (_split_unit(h)[0] for h in header):  # "speed [km/h]" for speed
                col[key] = [_split_unit(h)[0] for h in header].index(name)
            elif key in mapping.columns or key in REQUIRED:
                raise InputError(f"{csv_path}: no column {name!r} for {key} (columns: "
                                 f"{', '.join(header)}, separated by {delim!r}; map it with "
                                 f"--column {key}=NAME, or state --delimiter)")
        written = {k: _split_unit(header[i])[1] for k, i in col.items()}
        first = next(reader, None)
        units_row = first is not None and _is_units_row(first, col)
        if units_row:  # a row of units under the header (a recorder's export)
            written = {k: u or (first[i].strip() if i < len(first) else "") or None
                       for (k, u), i in zip(written.items(), col.values())}
        res.file_units = _written_units(written, mapping, csv_path)
        if "balise" in col and "balise_position" not in col and line is None:
            raise InputError("balise passages need their positions: give --line "
                             "line.yaml or a balise_position column")
        fac = {k: mapping.factor(k) for k in col if k in UNITS}
        pct = [k for k in ("traction", "braking") if k in col
               and mapping.units.get(k) == "percent"]
        clocks = {k: _Clock(k, fac.get(k, 1.0)) for k in ("time", "train_time")}
        lookup = line.balise_by_id if line is not None else (lambda i: None)
        parsed = []
        rows = reader if first is None else itertools.chain([] if units_row else [first], reader)
        for lineno, row in enumerate(rows, start=pre + (3 if units_row else 2)):
            if not row or all(not c.strip() for c in row):
                continue
            res.rows += 1
            try:
                if len(row) > len(header) and any(c.strip() for c in row[len(header):]):
                    raise BadRow("ragged", f"{len(row)} cells under a header of {len(header)}"
                                 + (" (a decimal comma in a comma-separated file? such cells "
                                    "must be quoted)" if delim == "," else ""))
                if with_comma:
                    dotted = next((k for k in NUMERIC if k in col and col[k] < len(row)
                                   and "." in row[col[k]]), None)
                    if dotted is not None:  # 1.002 in a decimal-comma file: 1002, or 1.002?
                        raise BadRow("thousands", f"{dotted} {row[col[dotted]].strip()!r} has a "
                                     "'.' in a file whose decimal mark is ',': a thousands "
                                     "separator? (write numbers without one)")
                    row = [c.replace(",", ".") for c in row]
                r = _parse(row, lineno, col, fac, lookup, clocks)
                for k in pct:  # a command beyond its maximum: a column in another unit
                    if r.values.get(k, 0.0) > 100.0 * fac[k] * (1 + 1e-9):
                        raise BadRow("out_of_range", f"{k} {r.values[k] / fac[k]:g} % is above "
                                     f"100 % of {k}_max (is the column in percent?)")
                parsed.append(r)
            except _TimeOnly:
                res.rows -= 1
                res.time_only += 1
            except BadRow as e:
                _bad(e, lineno, csv_path, skip_bad_rows, res)
    except csv.Error as e:
        raise InputError(f"{csv_path}: not a readable CSV ({e})") from None
    res.rollovers = [(k, ln) for k, c in clocks.items() for ln in c.rollovers]
    if sort:
        order = sorted(range(len(parsed)), key=lambda i: parsed[i].time)
        res.moved = sum(1 for i, j in enumerate(order) if i != j)
        parsed = [parsed[i] for i in order]
    # The reference time orders the log (the recorder's clock, as it wrote the rows). The
    # train's stamps need not follow it: a link with jitter delivers samples out of order,
    # and the bag keeps them in arrival order as a recorder does.
    rows = []
    last_t = -math.inf
    for r in parsed:
        if r.time < last_t:
            _bad(BadRow("out_of_order", f"time {r.time:.9g} s is before the previous row's "
                        f"{last_t:.9g} s (rows out of order: --sort sorts them by time)"),
                 r.line, csv_path, skip_bad_rows, res)
            continue
        last_t = r.time
        rows.append(r)
    return rows


def _bad(e: BadRow, lineno: int, csv_path, skip_bad_rows: bool, res: Result) -> None:
    if not skip_bad_rows:
        raise InputError(f"{csv_path} line {lineno}: {e} (use --skip-bad-rows to leave such "
                         "rows out)") from None
    res.skipped[e.reason] += 1
    if len(res.first_skipped) < 5:
        res.first_skipped.append(f"line {lineno}: {e}")


# s: a train clock that goes back by more than this while the reference clock runs on has
# restarted (an on-board computer rebooted: its clock from 0 again), not delivered a sample late
# (a link's delays are seconds at most)
CLOCK_RESTART = 60.0


def _clock_restarts(odo: list[_Row]) -> list[int]:
    """Indices (log order) where each run of the train clock starts: 0, then every row whose
    train stamp lies more than ``CLOCK_RESTART`` s before the highest of its run while its
    reference time is after that sample's. Numbered by the stamps across such a restart, the
    log of a clock rebooted after an hour was 100 samples "of 36,050", 99.7 % lost."""
    starts = [0]
    hi_tt, hi_t = -math.inf, -math.inf
    for i, r in enumerate(odo):
        if r.train_time < hi_tt - CLOCK_RESTART and r.time >= hi_t:
            starts.append(i)
            hi_tt, hi_t = r.train_time, r.time
        elif r.train_time > hi_tt:
            hi_tt, hi_t = r.train_time, r.time
    return starts


def _number_odometer(odo: list[_Row], res: Result) -> None:
    """Each odometer row's ``seq``: the log's counter, or numbered from the train clock's
    period; the samples lost (gaps) are recorded in ``res``."""
    counted = [r for r in odo if "sample" in r.values]
    if counted and len(counted) == len(odo):
        res.numbering = "counter"
        seq = np.array([r.values["sample"] for r in odo], dtype=np.int64)
    else:
        # a counter column with empty cells is no counter (mixing would number twice)
        res.numbering = "period"
        stamps = np.array([r.train_time for r in odo])
        res.period = sampling_period(stamps)
        seq = np.empty(stamps.size, dtype=np.int64)
        starts = _clock_restarts(odo)
        res.clock_restarts = [odo[i].line for i in starts[1:]]
        base = 0
        for a, b in zip(starts, starts[1:] + [len(odo)]):
            # numbered on across a restart of the train clock (a sample counter would count
            # on): the samples between the last before it and the first after are not known
            seq[a:b] = base + number_samples(stamps[a:b], res.period)
            base = int(seq[a:b].max())
    for r, s in zip(odo, seq):
        r.values["seq"] = int(s) % (SEQ_MAX + 1)
    # the gaps in sample order (a sample delivered late is not lost; one delivered twice is
    # counted once), per run of the counter: unwrapped past 2^32 - 1 (a counter that wraps
    # lost nothing) and restarted where it goes back while the train clock runs on (the
    # samples between two runs are not counted)
    q, runs = counter_runs(seq, np.array([r.train_time for r in odo]))
    per_run = counter_gaps(q, runs)
    res.samples = sum(n for _, n, _ in per_run)
    res.lost = res.samples - sum(k for k, _, _ in per_run)
    res.restarts = len(per_run) - 1
    res.gaps = []
    t0 = None
    for run in np.unique(runs):  # where the gaps are: the line after each, and its time
        idx = np.flatnonzero(runs == run)
        order = idx[np.argsort(q[idx], kind="stable")]
        steps = np.diff(q[order])
        t0 = odo[order[0]].train_time if t0 is None else t0
        res.gaps += [(odo[order[i + 1]].line, int(steps[i] - 1),
                      odo[order[i + 1]].train_time - t0) for i in np.flatnonzero(steps > 1)]


def _write(rows: list[_Row], mapping: Mapping, writer: BagWriter, res: Result) -> None:
    n_bal = 0
    for r in rows:
        v = r.values
        t_ns = int(round(r.time * 1e9))
        if "speed" in v:
            writer.write("odometer", r.train_time, {
                "seq": v["seq"], "distance": v["distance"], "speed": v["speed"],
                "speed_variance": mapping.speed_std ** 2}, t_ns=t_ns)
            res.written["odometer"] += 1
        if "balise_id" in v:
            n_bal += 1
            writer.write("balise", r.train_time, {
                "seq": n_bal, "balise_id": v["balise_id"], "position": v["balise_position"],
                "position_variance": mapping.balise_std ** 2}, t_ns=t_ns)
            res.written["balise"] += 1
        if "traction" in v or "braking" in v:
            writer.write("control", r.time, {
                "target_acceleration": v.get("traction", 0.0) - v.get("braking", 0.0)},
                t_ns=t_ns)
            res.written["control"] += 1


# ------------------------------------------------------------------------------------------------
# Command line
# ------------------------------------------------------------------------------------------------

def report(res: Result, out: str) -> list[str]:
    """The summary printed after a conversion: counts, lost samples and where, midnights."""
    counts = ", ".join(f"{k} {n}" for k, n in sorted(res.written.items()))
    lines = [f"wrote {out}: {res.rows} rows -> {counts}"]
    if res.numbering == "counter":
        how = "by the log's sample counter"
    elif math.isfinite(res.period):
        how = (f"from the train clock's period {res.period:.6g} s (estimated from the "
               "stamps)")
    else:
        how = "one per row (a single sample: no period)"
    share = res.lost / res.samples if res.samples else 0.0
    lines.append(f"odometer samples numbered {how}: {res.samples - res.lost} of "
                 f"{res.samples} in the log, {res.lost} lost ({100 * share:.1f} %) in "
                 f"{len(res.gaps)} gaps" + (f"; the counter restarted {res.restarts} "
                                             f"time{'s' if res.restarts > 1 else ''} (samples "
                                             f"between its runs not counted)"
                                             if res.restarts else ""))
    if res.gaps:
        big = sorted(res.gaps, key=lambda g: (-g[1], g[0]))[:3]
        lines.append("  largest gaps: " + "; ".join(
            f"{n} before line {ln} ({tt:.1f} s after the first sample)" for ln, n, tt in big))
        first = res.gaps[:5]
        lines.append("  first gaps at lines " + ", ".join(
            f"{ln} ({n})" for ln, n, _ in first) + (" ..." if len(res.gaps) > 5 else ""))
    delim, dec, found = res.dialect
    if (delim, dec) != (",", "."):  # not the plain form: say how it was read, and whence
        lines.append(f"read with the delimiter {delim!r} and the decimal mark {dec!r}"
                     + (f" ({found} found from the file's first lines: state them with "
                        "--delimiter, --decimal or the map if that is wrong)" if found else ""))
    if res.encoding:
        lines.append(f"read as {res.encoding.upper()} (its byte-order mark)")
    if res.preamble:
        lines.append(f"{res.preamble} line{'s' if res.preamble > 1 else ''} before the header "
                     "left out (comments, a sep= line)")
    if res.clock_restarts:
        lines.append(f"the train clock restarted {len(res.clock_restarts)} time"
                     f"{'s' if len(res.clock_restarts) > 1 else ''} (at line"
                     f"{'s' if len(res.clock_restarts) > 1 else ''} "
                     f"{', '.join(map(str, res.clock_restarts[:5]))}: its stamps went back while "
                     "the reference clock ran on): numbered on across it, the samples between "
                     "not counted")
    if res.time_only:
        lines.append(f"{res.time_only} rows hold a time and nothing else (a row written for a "
                     "sample that did not come): left out, not counted as bad")
    if res.file_units:
        lines.append("units as the file writes them: " + ", ".join(
            f"{k} {u}" for k, u in res.file_units.items()))
    for key, ln in res.rollovers:
        lines.append(f"{key} crossed midnight at line {ln}: a day added from there on")
    if res.moved:
        lines.append(f"--sort moved {res.moved} rows into time order")
    if res.skipped:
        lines.append(f"skipped {sum(res.skipped.values())} bad rows: "
                     + ", ".join(f"{k} {n}" for k, n in sorted(res.skipped.items())))
        lines += [f"  {s}" for s in res.first_skipped]
    return lines


@pipe_safe
def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="csv2bag", description=__doc__.splitlines()[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter,
                                epilog="\n".join(__doc__.splitlines()[2:]))
    p.add_argument("csv", help="the recorder's CSV log (a header row, then one row per event)")
    p.add_argument("--out", required=True, help="the bag directory to write (must not exist)")
    p.add_argument("--map", help="YAML: columns, units, traction_max, braking_max, ...")
    p.add_argument("--line", help="line.yaml: balise positions by id")
    p.add_argument("--column", action="append", metavar="KEY=NAME",
                   help="CSV column of a quantity, e.g. speed=v_kmh (repeatable)")
    p.add_argument("--unit", action="append", metavar="KEY=UNIT",
                   help="unit of a quantity, e.g. speed=km/h (repeatable)")
    p.add_argument("--delimiter", metavar="D",
                   help="the field separator: , ; | or tab (default: found from the file)")
    p.add_argument("--decimal", choices=(".", ","),
                   help="the decimal mark of numbers (default: found from the file)")
    p.add_argument("--encoding", metavar="E",
                   help="the text's encoding, e.g. cp1252 (default utf-8, with or without "
                        "a byte-order mark)")
    p.add_argument("--sort", action="store_true",
                   help="sort the rows by the reference time first (default: rows out of "
                        "order are bad rows)")
    p.add_argument("--skip-bad-rows", action="store_true",
                   help="leave bad rows out and count them (default: stop at the first)")
    p.add_argument("--max-skipped", default=MAX_SKIPPED, metavar="N|P%",
                   help="with --skip-bad-rows, more skipped rows than this is an error: a "
                        f"number of rows or a percentage of the data rows (default "
                        f"{MAX_SKIPPED.replace('%', '%%')})")
    p.add_argument("--namespace", default="/train", help="topic namespace (default /train)")
    args = p.parse_args(argv)
    import warnings

    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always", ConfigWarning)
            mapping = load_mapping(args.map, args.column, args.unit, args.delimiter,
                                   args.decimal, args.encoding)
            line = load_line(args.line) if args.line else None
        for w in caught:  # extra keys in the map or the line file: one line each
            print(f"csv2bag: warning: {w.message}", file=sys.stderr)
        max_skipped_rows(args.max_skipped, 0)  # a bad value fails before any row is read
        res = convert(args.csv, args.out, mapping, line, args.skip_bad_rows, args.namespace,
                      sort=args.sort, max_skipped=args.max_skipped)
    except (InputError, ConfigError, BagError) as e:
        print(f"csv2bag: {e}", file=sys.stderr)
        return 2
    print("\n".join(report(res, args.out)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
