"""`diagnose` gives the same verdict through a bag and through a recorder's CSV log of the same
run: one case per cause diagnose knows, the link's losses as rows missing from the log.

The CSV comes from an independent writer (tests/helpers/recorder_csv.py: the bag's MCAP read
with the mcap libraries, one row per message in log-time order; nothing of the generator or of
csv2bag), once with the odometer's sample counter and once without it (csv2bag then numbers the
samples from the train clock's period, so the missing rows count as lost). The nominal run, a
bursty link and a braking-rate change run by default, with both logs; the other causes are
``slow``, each with one of the two logs in turn (benchmarks/bench_csv2bag.py runs every cause
with both and docs/benchmarks.md has the table).
"""

from __future__ import annotations

import contextlib
import importlib.util
import io
import json
from pathlib import Path

import numpy as np
import pytest
from train_core.bagio import read_bag

from train_estimation.tools import csv2bag, diagnose
from train_sim.cases import CAUSES, make_case
from train_sim.generate import generate

HELPER = Path(__file__).parent / "helpers" / "recorder_csv.py"
DEFAULT = ("none", "bursty_link", "braking_rate")
ALL = ("none",) + CAUSES


def _writer():
    spec = importlib.util.spec_from_file_location("recorder_csv", HELPER)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod.write_csv


def _verdict(bag: Path, paths: dict, out: Path) -> str:
    with contextlib.redirect_stdout(io.StringIO()), \
            contextlib.redirect_stderr(io.StringIO()) as err:
        rc = diagnose.main(["--bag", str(bag), "--line", str(paths["line"]), "--train",
                            str(paths["train"]), "--out", str(out), "--quiet", "--no-plots"])
    assert rc == 0, err.getvalue()
    return json.loads((out / "report.json").read_text())["cause"]


def _seq_by_stamp(bag: Path) -> dict:
    return {s: f["seq"] for _, s, f in read_bag(bag).topics["odometer"]}


@pytest.mark.parametrize("cause", [c if c in DEFAULT else pytest.param(c, marks=pytest.mark.slow)
                                   for c in ALL])
def test_the_same_verdict_through_the_bag_and_through_a_recorders_csv(cause, tmp_path):
    # the benchmark's first seed of this cause (benchmarks/bench_csv2bag.py)
    case = make_case(np.random.default_rng([0, 48, ALL.index(cause)]),
                     None if cause == "none" else cause, "plain")
    paths = case.write(tmp_path / "case")
    bag = tmp_path / "bag"
    generate(case.scenario, bag, measured=True)
    original = read_bag(bag)
    verdict = _verdict(bag, paths, tmp_path / "diag_bag")
    write_csv = _writer()
    # both logs for the default cases; one each for the others, in turn (the benchmark writes
    # both for every cause)
    counters = ("seq", "none") if cause in DEFAULT else (("seq", "none")[ALL.index(cause) % 2],)
    for counter in counters:
        log, mp, out = (tmp_path / f"{counter}{x}" for x in (".csv", ".yaml", "_bag"))
        counts = write_csv(bag, log, mp, counter=counter)
        with contextlib.redirect_stdout(io.StringIO()) as said:
            assert csv2bag.main([str(log), "--map", str(mp), "--out", str(out)]) == 0
        converted = read_bag(out)
        for topic in ("odometer", "balise", "control"):
            assert len(converted.topics[topic]) == len(original.topics[topic]) \
                == counts[topic], topic
        # the sample numbers: the counter's, or from the period, which counts every loss
        # the counter shows (the same numbers but for the first's)
        want, got = _seq_by_stamp(bag), _seq_by_stamp(out)
        assert want.keys() == got.keys()
        first = min(want, key=want.get)
        assert all(got[s] - got[first] == want[s] - want[first] for s in want), counter
        lost = len(set(range(min(want.values()), max(want.values()) + 1)) - set(want.values()))
        assert f"{lost} lost" in said.getvalue(), said.getvalue()
        assert _verdict(out, paths, tmp_path / f"diag_{counter}") == verdict, counter
