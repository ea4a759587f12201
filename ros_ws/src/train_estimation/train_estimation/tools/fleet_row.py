"""`fleet`'s row of one bag: what its analysis found (:mod:`.fleet_dask`), what runs.csv, the
cache and the history hold of it (:mod:`.fleet_report`, :mod:`.fleet`), and the consensus'
input built from it (:func:`consensus_rows`).

The cache's and the history's JSON of a row is :meth:`BagRow.to_json` (every field, null where
unset); :meth:`BagRow.from_json` reads it back, a field missing from an older file as None.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path

PARAMS = ("braking_rate", "mass", "odometer_scale")  # the per-train parameters of the consensus


@dataclass(frozen=True)
class BagRow:
    """One bag of a fleet run: the task, the analysis' results, and where the run put it.
    Unset (None): not analysed, not found, or not identifiable."""

    train: str  # the train's name (manifest; or the bag's folder or name)
    bag: str  # path of the bag
    line_file: str  # path of the line.yaml it is analysed with
    train_file: str  # path of the train.yaml
    # the run's time: the manifest's (any unit, one clock across days; the fleet simulator:
    # hours), else the bag's first log time in hours
    time: float | None = None
    key: str | None = None  # SHA-256 of the bag, line, train and analysis version (the cache)
    error: str | None = None  # why the bag could not be analysed, one line; None: analysed
    traceback_at: str | None = None  # the function the analysis failed in
    # check_bag's topic health: messages, and the fraction of sequence numbers received (1)
    line: str | None = None  # the line's name
    odometer_count: int | None = None
    odometer_received: float | None = None
    balise_count: int | None = None
    balise_received: float | None = None
    control_count: int | None = None
    control_received: float | None = None
    duration_s: float | None = None  # s, from the first to the last odometer stamp
    # identify: braking rate f (1) and mass (kg) with standard errors, where identifiable
    identify_braking_rate: float | None = None
    identify_braking_rate_se: float | None = None
    identify_mass: float | None = None
    identify_mass_se: float | None = None
    identify_error: str | None = None  # why identify could not fit the run
    # diagnose (Cause.fleet_row)
    cause: str | None = None  # the verdict
    accepted: str | None = None  # the accepted causes, joined by "+"
    gradient_start: float | None = None  # m, an accepted gradient section's start
    gradient_end: float | None = None  # m, its end
    gradient_permille: float | None = None  # per mille, true minus mapped
    gradient_se: float | None = None  # per mille, its standard error
    gradient_score: float | None = None  # diagnose's score of the section
    gradient_v2: float | None = None  # m^2/s^2, mean square speed over the section
    resistance_v_ref: float | None = None  # m/s, the speed the resistance force is taken at
    resistance_dforce: float | None = None  # N, fitted minus believed force at v_ref
    resistance_dforce_se: float | None = None  # N
    # braking rate f (1) and mass (kg) for the trends: identify's where it identifies them,
    # else diagnose's; ``*_source`` says which ("identify", "diagnose", None)
    braking_rate: float | None = None
    braking_rate_se: float | None = None
    braking_rate_source: str | None = None
    mass: float | None = None
    mass_se: float | None = None
    mass_source: str | None = None
    odometer_scale: float | None = None  # distance counted per metre run (1)
    odometer_scale_se: float | None = None
    coverage: list | None = None  # m, [first, last] track position the run covered
    # diagnose's balise innovations of the run ({z, c, info, speed, position}: the reader's
    # checks pooled over the train's passes, core.offline.fleet_readers); not in runs.csv
    balise: dict | None = None
    seconds: float | None = None  # s, the analysis' wall time on its worker
    worker: str | None = None  # the address of the Dask worker that analysed it
    cached: bool | None = None  # taken from the cache (True) or analysed by this run
    manifest_day: str | None = None  # the manifest's day column
    day: str | None = None  # the day it belongs to in the history

    def to_json(self) -> dict:
        """Every field (plain JSON types where the values are)."""
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}

    @classmethod
    def from_json(cls, d: dict) -> BagRow:
        """A row of :meth:`to_json` (a field it lacks: None; keys that are no field: left out).
        TypeError when ``d`` is not a JSON object."""
        if not isinstance(d, dict):
            raise TypeError(f"a row is a JSON object, not {type(d).__name__}")
        return cls(**{f.name: _typed(f, d.get(f.name)) for f in dataclasses.fields(cls)})


def consensus_rows(rows: list[BagRow]) -> list[dict]:
    """The table's rows in core.offline.fleet's input format."""
    out = []
    for r in rows:
        c = {"train": r.train, "line": r.line or Path(r.line_file).stem,
             "time": r.time or 0.0, "bag": r.bag, "error": r.error,
             "coverage": r.coverage, "day": r.day, "balise": r.balise}
        if r.gradient_se:
            c["gradient"] = {"start": r.gradient_start, "end": r.gradient_end,
                             "permille": r.gradient_permille, "se": r.gradient_se,
                             "v2": r.gradient_v2}
        if r.resistance_dforce_se:
            c["resistance"] = {"value": r.resistance_dforce,
                               "se": r.resistance_dforce_se}
        for p in PARAMS:
            if getattr(r, f"{p}_se"):
                c[p] = {"value": getattr(r, p), "se": getattr(r, f"{p}_se")}
        out.append(c)
    return out


def _typed(f: dataclasses.Field, value):
    """A field's value as its type says: a number written as text (a history exported or merged
    by hand: "0.60") is read as the number, not skipped by the consensus without a word; text
    that is no number in a numeric field is a ValueError naming the field."""
    kind = str(f.type)
    if isinstance(value, str) and ("float" in kind or "int" in kind):
        try:
            x = float(value)
        except ValueError:
            raise ValueError(f"{f.name} {value!r} is not a number") from None
        return int(x) if "int" in kind and "float" not in kind and x.is_integer() else x
    if isinstance(value, bool) and ("float" in kind or "int" in kind) and "bool" not in kind:
        raise ValueError(f"{f.name} {value!r} is not a number")
    return value
