"""Real lines from TTOBench's track files into the project's ``line.yaml``.

TTOBench (github.com/dkouzoup/TTOBench, BSD-2-Clause; Kouzoupis, Pendharkar and Corman, "TTOBench
-- an Open-Source Library for Train Trajectory Optimization", Operations Research Forum 4, 2023)
publishes real tracks as JSON. Its schema (``tracks/README.md`` there) and how each field maps:

- ``metadata``: ``id`` (letters, digits, underscores) -> ``name``; ``library version``,
  ``license``, ``created by`` -> the header comment.
- ``stops``: ``{"unit": "m" | "km", "values": [0, ..., S]}``, strictly increasing from 0; the
  last is the track's length S -> ``length`` and ``stations`` (named ``S1`` .. ``Sn`` in
  running order; TTOBench gives positions only).
- ``speed limits``: ``{"units": {"position": "m" | "km", "velocity": "km/h" | "m/s"},
  "values": [[position, limit], ...]}``, each pair the start of a section that runs to the next
  pair (the last to S); first position 0, strictly increasing, each < S -> ``max_speed`` (the
  highest limit, m/s) and one ``speed_limits`` section per stretch below it.
- ``gradients`` (optional; absent = level): ``{"units": {"position": .., "slope": "permil"},
  "values": [[position, slope], ...]}``, sections as above; positive = uphill in the running
  direction, as in line.yaml -> ``gradients``, one section per pair, no gap.
- ``curvatures`` (optional; absent = straight): ``[[position, radius at start, radius at
  end], ...]`` in m or km, "infinity" for straight; a positive radius turns right, a negative
  one left; different radii: a clothoid -> the extra key ``curves`` (every section that is not
  straight: ``{start, end, radius_start, radius_end}`` in m, signed; ``null`` for an infinite
  end of a clothoid). The simulator and the estimators do not model curve resistance: the
  key is kept for the reader and for a model that will.
- ``altitude`` (optional): the altitude at the start -> the header comment.

TTOBench has no balises: the importer places them as a railway does, one ``balise_before_stop``
m before each stop (after the origin: one that far beyond it), and more, evenly spaced, where
two are further apart than ``balise_spacing`` m.

Every check of TTOBench's own validator (``utils/validateTracks.py``) is applied, and a gradient
beyond line.yaml's +-60 per mille is refused; a field outside the schema is named in a warning.
Errors are :class:`~train_core.config.ConfigError` with the file, the field and what is allowed.

    python -m train_core.ttobench TRACK.json --out line.yaml

Pure module: json, PyYAML and the shared model.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import math
import os
import sys
import warnings
from pathlib import Path

import yaml

from train_core.config import ConfigError, ConfigWarning, show_config_warnings_on_one_line
from train_core.model import line_from_dict

__all__ = ["find_track", "load_track", "track_to_line", "write_line", "resolve_line", "main"]

FIELDS_REQUIRED = ("metadata", "stops", "speed limits")
FIELDS_OPTIONAL = ("altitude", "gradients", "curvatures")
_LENGTH = {"m": 1.0, "km": 1000.0}
_SPEED = {"m/s": 1.0, "km/h": 1.0 / 3.6}
MAX_PERMILLE = 60.0  # line.yaml's bound on a gradient
MAX_SPEED = 170.0  # m/s (612 km/h): above any railway's, maglev included: a unit slip
MAX_BALISES = 100_000  # balises the importer places: more is a unit slip or a spacing typo

# where a scenario's ``line: ttobench:ID`` is looked for (resolve_line)
LINES_ENV = "TRAIN_LINES_DIR"
SOURCE = "https://github.com/dkouzoup/TTOBench"  # for the messages and the docs only
HOW_TO_GET = (f"get it from TTOBench ({SOURCE}, BSD-2-Clause): tracks/ID.json, e.g. `git clone "
              f"{SOURCE}` and copy its tracks/*.json there")
# the importer's version: a converted file from an older importer is made again
_VERSION = "1"


def _fail(where: str, what: str) -> ConfigError:
    return ConfigError(f"{where}: {what}")


def _number(v, where: str) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise _fail(where, f"expected a finite number, got {v!r}")
    return float(v)


def _radius(v, where: str) -> float:
    """A radius: a number or "infinity" (TTOBench writes straight track so), in the file's
    unit; inf for straight."""
    if isinstance(v, str):
        try:
            r = float(v)
        except ValueError:
            raise _fail(where, f"expected a number or \"infinity\", got {v!r}") from None
        if math.isnan(r):
            raise _fail(where, f"expected a number or \"infinity\", got {v!r}")
        return r
    if isinstance(v, bool) or not isinstance(v, (int, float)) or math.isnan(v):
        raise _fail(where, f"expected a number or \"infinity\", got {v!r}")
    return float(v)


def _unit(d: dict, key: str, allowed: dict, where: str) -> float:
    u = d.get(key)
    if u not in allowed:
        raise _fail(where, f"unit {u!r}: allowed {', '.join(repr(a) for a in allowed)}")
    return allowed[u]


def _keys(d, expected: set, where: str) -> dict:
    """``d`` with the keys ``expected``: one missing is refused, one more is named in a warning
    (as a field outside the schema at the top: a producer may add a note)."""
    if not isinstance(d, dict) or not expected <= set(d):
        got = sorted(d) if isinstance(d, dict) else type(d).__name__
        raise _fail(where, f"expected the keys {sorted(expected)}, got {got}")
    extra = sorted(set(d) - expected)
    if extra:
        warnings.warn(f"{where}: keys outside TTOBench's schema ignored: "
                      f"{', '.join(map(repr, extra))}", ConfigWarning, stacklevel=3)
    return d


def _sections(data: dict, field: str, value_key: str, value_units: dict, length: float,
              where: str, n: int = 2) -> list[tuple]:
    """The pairs (or triples) of a sectioned field: [(start m, value...)] with the checks of
    TTOBench's validator: first position 0, strictly increasing, each below the length."""
    d = _keys(data[field], {"units", "values"}, f"{where}.{field}")
    units = d["units"]
    w = f"{where}.{field}.units"
    if not isinstance(units, dict):
        raise _fail(w, "expected a mapping of units")
    names = ["position", *value_units]
    _keys(units, set(names), w)
    k_pos = _unit(units, "position", _LENGTH, w)
    k_val = [_unit(units, name, allowed, w) for name, allowed in value_units.items()]
    vals = d["values"]
    if not isinstance(vals, list) or not vals:
        raise _fail(f"{where}.{field}.values", "expected a non-empty list")
    out, prev = [], None
    for i, v in enumerate(vals):
        wi = f"{where}.{field}.values[{i}]"
        if not isinstance(v, list) or len(v) != n:
            raise _fail(wi, f"expected a list of {n} ([{', '.join(names)}]), got {v!r}")
        pos = _number(v[0], wi + "[0]") * k_pos
        if i == 0 and pos != 0.0:
            raise _fail(wi, f"the first position must be 0, got {v[0]!r}")
        if prev is not None and pos <= prev:
            raise _fail(wi, f"positions must be strictly increasing ({pos:g} m after {prev:g} m)")
        if pos >= length:
            raise _fail(wi, f"position {pos:g} m is not before the track's end ({length:g} m, "
                            "the last stop)")
        if value_key == "curve":
            out.append((pos, *(_radius(x, f"{wi}[{j + 1}]") * k
                               for j, (x, k) in enumerate(zip(v[1:], k_val)))))
        else:
            out.append((pos, *(_number(x, f"{wi}[{j + 1}]") * k
                               for j, (x, k) in enumerate(zip(v[1:], k_val)))))
        prev = pos
    return out


def load_track(path: str | Path) -> dict:
    """A TTOBench track file's JSON; ConfigError when it cannot be read."""
    p = Path(path)
    try:
        data = json.loads(p.read_text(encoding="utf-8-sig"))  # a byte-order mark: dropped
    except FileNotFoundError:
        raise ConfigError(f"{p}: no such file") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"{p}: cannot read it ({exc})") from None
    except json.JSONDecodeError as exc:
        raise ConfigError(f"{p}: not JSON ({exc.msg} at line {exc.lineno})") from None
    if not isinstance(data, dict):
        raise ConfigError(f"{p}: expected a JSON object (TTOBench's track schema)")
    return data


def _balises(stops: list[float], length: float, spacing: float, before: float) -> list[float]:
    marks = []
    for i, s in enumerate(stops):
        x = s + before if i == 0 else s - before
        marks.append(min(max(x, 0.0), length))
    marks = sorted(set(round(x, 3) for x in marks))
    out = [marks[0]]
    for a, b in zip(marks, marks[1:]):
        k = math.ceil((b - a) / spacing)  # pieces, so that none is longer than the spacing
        out += [round(a + (b - a) * j / k, 3) for j in range(1, k)] + [b]
    return out


def track_to_line(track: dict, *, where: str = "track.json", balise_spacing: float = 500.0,
                  balise_before_stop: float = 40.0, dwell: float = 30.0) -> dict:
    """line.yaml's mapping (the keys of docs/interfaces.md, plus ``curves``) for a TTOBench
    track. Positions in m, speeds in m/s, gradients in per mille."""
    if not isinstance(track, dict):
        raise _fail(where, "expected a JSON object (TTOBench's track schema)")
    missing = [f for f in FIELDS_REQUIRED if f not in track]
    if missing:
        raise _fail(where, f"missing {', '.join(repr(m) for m in missing)} (a TTOBench track "
                           f"has {', '.join(FIELDS_REQUIRED)}; optional "
                           f"{', '.join(FIELDS_OPTIONAL)})")
    extra = [k for k in track if k not in FIELDS_REQUIRED + FIELDS_OPTIONAL]
    if extra:
        warnings.warn(f"{where}: fields outside TTOBench's schema ignored: "
                      f"{', '.join(map(repr, extra))}", ConfigWarning, stacklevel=2)
    if not (balise_spacing > 0 and balise_before_stop >= 0 and dwell >= 0):
        raise ConfigError("balise spacing must be > 0 m, the balise before a stop >= 0 m and "
                          "the dwell >= 0 s")
    meta = track["metadata"]
    if not isinstance(meta, dict) or not isinstance(meta.get("id"), str) or not meta["id"]:
        raise _fail(f"{where}.metadata", "expected a mapping with a non-empty 'id'")
    # stops: the track's length and its stations
    st = _keys(track["stops"], {"unit", "values"}, f"{where}.stops")
    k = _unit(st, "unit", _LENGTH, f"{where}.stops")
    if not isinstance(st["values"], list) or len(st["values"]) < 2:
        raise _fail(f"{where}.stops.values", "expected at least two stops (0 and the end)")
    stops = [_number(v, f"{where}.stops.values[{i}]") * k for i, v in enumerate(st["values"])]
    if stops[0] != 0.0:
        raise _fail(f"{where}.stops.values[0]", f"the first stop must be 0, got {stops[0]:g}")
    for i in range(1, len(stops)):
        if stops[i] <= stops[i - 1]:
            raise _fail(f"{where}.stops.values[{i}]", "stops must be strictly increasing "
                                                      f"({stops[i]:g} m after {stops[i - 1]:g} m)")
    length = stops[-1]
    if length / balise_spacing + len(stops) > MAX_BALISES:
        raise _fail(f"{where}.stops", f"{length:g} m at a balise every {balise_spacing:g} m "
                                      f"is more than {MAX_BALISES:,} balises: check the stops' "
                                      f"unit, or the balise spacing")

    def ends(secs):
        return [(s[0], (secs[i + 1][0] if i + 1 < len(secs) else length), *s[1:])
                for i, s in enumerate(secs)]

    limits = ends(_sections(track, "speed limits", "speed", {"velocity": _SPEED}, length, where))
    for (a, _b, v), i in zip(limits, range(len(limits))):
        if v <= 0:
            raise _fail(f"{where}.speed limits.values[{i}]", f"a speed limit must be > 0, got "
                                                             f"{v:g} m/s at {a:g} m")
        if v > MAX_SPEED:
            raise _fail(f"{where}.speed limits.values[{i}]",
                        f"{v:g} m/s ({v * 3.6:g} km/h) at {a:g} m is faster than any railway "
                        f"(<= {MAX_SPEED:g} m/s): check its unit")
    vmax = max(v for _, _, v in limits)
    grads = [(0.0, length, 0.0)]
    if "gradients" in track:
        grads = ends(_sections(track, "gradients", "slope", {"slope": {"permil": 1.0}}, length,
                               where))
        for i, (a, _b, g) in enumerate(grads):
            if abs(g) > MAX_PERMILLE:
                raise _fail(f"{where}.gradients.values[{i}]",
                            f"{g:g} per mille at {a:g} m is beyond line.yaml's "
                            f"+-{MAX_PERMILLE:g} per mille")
    curves = []
    if "curvatures" in track:
        for a, b, r0, r1 in ends(_sections(
                track, "curvatures", "curve", {"radius at start": _LENGTH,
                                               "radius at end": _LENGTH}, length, where, n=3)):
            if r0 == 0 or r1 == 0:
                raise _fail(f"{where}.curvatures", f"a radius of 0 at {a:g} m (straight track "
                                                   "is \"infinity\")")
            if math.isinf(r0) and math.isinf(r1):
                continue  # straight
            curves.append({"start": a, "end": b,
                           "radius_start": None if math.isinf(r0) else r0,
                           "radius_end": None if math.isinf(r1) else r1})
    rnd = lambda x: round(float(x), 6)  # noqa: E731 - one rounding for every number written
    line = {
        "name": meta["id"],
        "length": rnd(length),
        "max_speed": rnd(vmax),
        "speed_limits": [{"start": rnd(a), "end": rnd(b), "speed": rnd(v)}
                         for a, b, v in limits if v < vmax],
        "gradients": [{"start": rnd(a), "end": rnd(b), "permille": rnd(g)} for a, b, g in grads],
        "stations": [{"name": f"S{i + 1}", "position": rnd(s), "dwell": dwell}
                     for i, s in enumerate(stops)],
        "balises": [{"id": i + 1, "position": rnd(x)} for i, x in enumerate(
            _balises(stops, length, balise_spacing, balise_before_stop))],
    }
    if curves:
        line["curves"] = [{k2: (rnd(v) if v is not None else None) for k2, v in c.items()}
                          for c in curves]
    with warnings.catch_warnings():
        # curves is this importer's extra key: documented, not a typo to warn about
        warnings.simplefilter("ignore", ConfigWarning)
        line_from_dict(line, f"{where} (converted)")  # the project's own checks
    return line


def header(track: dict, source: str) -> str:
    meta = track.get("metadata") or {}
    alt = track.get("altitude")
    lines = [f"Converted from TTOBench's track {meta.get('id')} ({source}) by train_core.ttobench.",
             f"TTOBench: {SOURCE} ({meta.get('library version', 'version not stated')}; "
             f"licence: {meta.get('license', 'BSD-2-Clause')}; "
             f"created by {meta.get('created by', 'not stated')}).",
             "Stations S1..Sn are TTOBench's stops; balises are placed by the importer (TTOBench "
             "has none); curves: signed radii (m, + right), not modelled by the simulator."]
    if isinstance(alt, dict) and "value" in alt:
        lines.append(f"Altitude at the start: {alt['value']} {alt.get('unit', 'm')}.")
    # one comment line each: a value holding a newline ("A. Person\nmax_speed: 1") would
    # otherwise end the comment and become a key of the file
    return "".join(f"# {' '.join(x.split())}\n" for x in lines)


def write_line(line: dict, path: str | Path, head: str = "") -> Path:
    """line.yaml at ``path`` (written whole, then renamed: a reader never sees half a file)."""
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    tmp = p.with_name(f".{p.name}.{os.getpid()}.tmp")
    tmp.write_text(head + yaml.safe_dump(line, sort_keys=False, default_flow_style=None,
                                         width=100), encoding="utf-8")
    tmp.replace(p)
    return p


# ------------------------------------------------------------------------------------------------
# Scenarios: ``line: ttobench:ID``, found at run time (the data is not in the repository)
# ------------------------------------------------------------------------------------------------

def search_dirs() -> list[Path]:
    """Where a track file is looked for: $TRAIN_LINES_DIR, then ``../shared/lines/`` beside the
    checkout (the source tree's repository)."""
    out = []
    if os.environ.get(LINES_ENV):
        out.append(Path(os.environ[LINES_ENV]))
    repo = Path(__file__).resolve().parents[4]  # ros_ws/src/train_core/train_core/ttobench.py
    if (repo / "ros_ws").is_dir():
        out.append(repo.parent / "shared" / "lines")
    return out


def find_track(track_id: str) -> Path:
    """The TTOBench file ``ID.json`` in :func:`search_dirs`; ConfigError naming the places
    looked in and how to get the file when it is in none."""
    dirs = search_dirs()
    for d in dirs:
        p = d / f"{track_id}.json"
        if p.is_file():
            return p
    where = " or ".join(str(d / f"{track_id}.json") for d in dirs) or "(no directory)"
    raise ConfigError(
        f"the real line {track_id} is not here: put TTOBench's {track_id}.json in {where} "
        f"(a directory of track files can also be named with {LINES_ENV}=DIR); "
        + HOW_TO_GET.replace("ID", track_id))


def cache_dir() -> Path:
    repo = Path(__file__).resolve().parents[4]
    if (repo / "ros_ws").is_dir():
        return repo / ".cache" / "lines"
    import tempfile

    return Path(tempfile.gettempdir()) / "train_lines"


def resolve_line(track_id: str, **options) -> Path:
    """line.yaml of TTOBench track ``track_id`` (found by :func:`find_track`), converted once
    into the cache (named by the track file's content, the options and the importer's
    version) and read from there afterwards."""
    src = find_track(track_id)
    raw = src.read_bytes()
    key = hashlib.sha256(raw + json.dumps([options, _VERSION], sort_keys=True).encode()
                         ).hexdigest()[:12]
    out = cache_dir() / f"{track_id}-{key}.yaml"
    if not out.is_file():
        track = load_track(src)
        write_line(track_to_line(track, where=str(src), **options), out, header(track, src.name))
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(
        prog="ttobench2line",
        description="A TTOBench track file (JSON) into the project's line.yaml: gradients, speed "
                    "limits, stops as stations S1..Sn, balises placed by the importer, curve "
                    "radii kept as the extra key `curves`.",
        epilog=f"TTOBench: {SOURCE} (BSD-2-Clause), tracks/*.json. Errors name the field and "
               "exit 2. Docs: docs/real_lines.md.")
    p.add_argument("track", help="TTOBench track file, e.g. CN_Songjiazhuang_Yizhuang.json")
    p.add_argument("--out", required=True, help="line.yaml to write")
    p.add_argument("--balise-spacing", type=float, default=500.0,
                   help="m, the largest distance between two balises (default 500)")
    p.add_argument("--balise-before-stop", type=float, default=40.0,
                   help="m, a balise this far before each stop (after the origin) (default 40)")
    p.add_argument("--dwell", type=float, default=30.0,
                   help="s, planned dwell at each station (default 30)")
    args = p.parse_args(argv)
    show_config_warnings_on_one_line()  # a field outside the schema: one line on stderr
    try:
        track = load_track(args.track)
        line = track_to_line(track, where=args.track, balise_spacing=args.balise_spacing,
                             balise_before_stop=args.balise_before_stop, dwell=args.dwell)
        write_line(line, args.out, header(track, Path(args.track).name))
    except (ConfigError, OSError) as exc:
        print(f"ttobench2line: {' '.join(str(exc).split())}", file=sys.stderr)
        return 2
    g = [s["permille"] for s in line["gradients"]]
    print(f"wrote {args.out}: {line['name']}, {line['length']:.0f} m, {len(line['stations'])} "
          f"stations, {len(line['gradients'])} gradient sections ({min(g):+g} to {max(g):+g} "
          f"per mille), {len(line['speed_limits'])} speed restrictions below "
          f"{line['max_speed'] * 3.6:.0f} km/h, {len(line['balises'])} balises"
          + (f", {len(line['curves'])} curves" if line.get("curves") else ""))
    return 0


if __name__ == "__main__":
    sys.exit(main())
