"""One vocabulary of rejection reasons (core/reasons.py) everywhere."""

import math
import os
import sys

import numpy as np

from train_estimation.core import reasons as R
from train_estimation.core.online.replay import replay
from train_estimation.core.robust import robust_filter
from train_estimation.tools import check_bag
from train_estimation.tools.fuzz import EXPECTED, corrupt

sys.path.insert(0, os.path.dirname(__file__))
from clocks import adapter, restamp, run  # noqa: E402


def test_filters_reasons_are_the_vocabulary():
    assert set(robust_filter.REASONS) <= set(R.ALL)
    assert len(set(R.ALL)) == len(R.ALL)
    assert set(R.DESCRIPTION) == set(R.ALL)
    for names in EXPECTED.values():
        assert set(names) <= set(R.REJECTIONS)


def test_free_text_reasons_are_mapped_onto_names():
    # phrasings of core/braking/braking_filters.py (the adapter maps them)
    cases = {"non-finite measurement: [nan]": R.NON_FINITE,
             "non-positive or non-finite measurement variance: [0.0]": R.NON_POSITIVE_VARIANCE,
             "out-of-order or duplicate time stamp: 1.0 <= 2.0": R.OUT_OF_ORDER,
             "numerical failure: NaN likelihood": R.NUMERICAL_FAILURE,
             "bad mask shape: (2,) != (3,)": R.INVALID,
             R.OUTSIDE_GATE: R.OUTSIDE_GATE, "": ""}
    for text, name in cases.items():
        assert R.category(R.normalise(text)) == name, text


def test_every_estimator_counts_rejections_by_vocabulary_name():
    sc, res = run(duration=30.0)
    ev, counts = corrupt(restamp(res.events()), np.random.default_rng(3), per_reading=3.0)
    assert sum(counts.values()) > 1000
    for kind in ("robust", "gsma", "sma", "rbpf", "qgrbpf"):
        _, r = replay(ev, adapter(sc, kind), 0.1)
        names = {k.split(":", 1)[1] for k in r.rejected}
        assert names <= set(R.REJECTIONS), (kind, names - set(R.REJECTIONS))
        assert all(R.category(text) in R.REJECTIONS for _, _, text in r.last_reasons)
        # each corruption was answered by one of its expected names
        expected = set().union(*(EXPECTED[k] for k in counts if k in EXPECTED))
        assert names <= expected, (kind, names - expected)


def test_check_bag_uses_the_vocabulary(tmp_path):
    from train_core.bagio import BagWriter

    bag = tmp_path / "bag"
    with BagWriter(bag) as w:
        for k, s in enumerate([1.0, 1.1, 1.05, 1.2]):
            w.write("odometer", s, {"seq": k, "distance": math.nan if k == 3 else 1.0,
                                    "speed": 1.0, "speed_variance": 0.01},
                    t_ns=10**9 + k * 10**8)  # arrival order: 1.05 arrives after 1.1
    h = check_bag.check(str(bag), plots=False)["topics"]["odometer"]
    assert h[R.OUT_OF_ORDER] == 1 and h[R.NON_FINITE] == 1
