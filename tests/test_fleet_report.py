"""The fleet report states the train-alert criterion that core/offline/fleet.py applies: every z in
the
per-train tables is shown with the critical value it was tested against, and a train-parameter
pair is alerted exactly when its |z| exceeds that value."""

import re

import numpy as np

from train_estimation.core.offline import fleet as F
from train_estimation.tools.fleet_report import report_md

INFO = {"when": "test", "cached": 0, "computed": 0, "wall_s": 0.0, "workers": "none"}
CELL = re.compile(r"([-+]?\d+\.\d+) \((\d+\.\d+)\)")


def _fleet(rng, n_trains, runs, f_bad=None, trend=None, tau=0.01):
    rows = []
    for i in range(n_trains):
        for k in range(runs):
            f = (f_bad if f_bad is not None and i == 0 else 1.0) + tau * rng.normal()
            if trend is not None and i == 1:
                f += trend * k
            r = {"train": f"T{i}", "line": "north", "time": 24.0 * k, "bag": f"T{i}-{k}",
                 "braking_rate": {"value": f + 0.02 * rng.normal(), "se": 0.02},
                 "mass": {"value": 288000 * (1 + 0.01 * rng.normal()), "se": 1000.0}}
            rows.append(r)
    return rows


def _tables(md: str) -> dict:
    """{(train, parameter, kind): (z, crit)} from the per-train tables of the report."""
    out, param = {}, None
    for line in md.splitlines():
        m = re.match(r"### (.+) per train", line)
        if m:
            param = m.group(1).replace(" ", "_")
            continue
        cells = [c.strip() for c in line.strip("|").split("|")]
        if param and len(cells) == 7 and cells[0].startswith("T"):
            for kind, cell in (("departs from the fleet", cells[4]),
                               ("trends in time", cells[6])):
                m = CELL.fullmatch(cell)
                if m:
                    out[(cells[0], param, kind)] = (float(m.group(1)), float(m.group(2)))
    return out


def test_stated_criterion_is_the_applied_one():
    t_above_normal = 0
    cases = [dict(n_trains=4, runs=3, trend=-0.03), dict(n_trains=6, runs=2, f_bad=0.9),
             dict(n_trains=8, runs=4, f_bad=0.85, trend=-0.02)]
    for seed, kw in enumerate(cases):
        res = F.consensus(_fleet(np.random.default_rng(seed), **kw))
        md = report_md(res, [], INFO, [])
        zc = res.trains["z_critical"]
        assert "Student-t quantile" in md and f"{zc:.2f}" in md
        tables = _tables(md)
        assert len(tables) >= kw["n_trains"] * 2, md
        alerted = {(a["train"], a["parameter"], a["kind"]) for a in res.train_alerts}
        for key, (z, crit) in tables.items():
            # printed to 2 decimals: a tie at that precision cannot be judged from the text
            if abs(abs(z) - crit) > 0.01:
                assert (abs(z) > crit) == (key in alerted), (key, z, crit)
            assert crit >= zc - 0.005
            t_above_normal += crit > zc + 0.01
        assert alerted <= set(tables)
    assert t_above_normal > 0  # the t-quantile, not the normal one, is what was applied


def test_first_lines_state_the_findings():
    """The report's top (the page's verdict box) names each alerted train with its parameter
    and size, or says that no train departs; the map errors likewise."""
    from train_estimation.tools.fleet_report import findings

    res = F.consensus(_fleet(np.random.default_rng(1), n_trains=6, runs=2, f_bad=0.9))
    md = report_md(res, [], INFO, [])
    top = md[:md.index("## Map errors")]
    assert res.train_alerts  # the case has one degraded train
    for a in res.train_alerts:
        assert f"**train {a['train']}**: {a['parameter'].replace('_', ' ')}" in top, top
    assert "- no map error" in top
    res = F.consensus(_fleet(np.random.default_rng(2), n_trains=6, runs=3))
    if not res.train_alerts:
        assert "- no train departs from the fleet or trends" in "\n".join(
            findings(res, [], {}))


def test_a_balise_reader_alert_is_among_the_findings():
    """A train whose balise reader's passes, pooled, show errors correlated from one reading to
    the next is named in the findings with the signature and the runs it was pooled over."""
    rng = np.random.default_rng(7)
    rows = _fleet(rng, n_trains=3, runs=20)
    for r in rows:  # each run's innovations; T0's reader drifts (AR(1) 0.9), the others not
        n, rho = 12, 0.9 if r["train"] == "T0" else 0.0
        e = np.empty(n)
        e[0] = rng.standard_normal()
        for k in range(1, n):
            e[k] = rho * e[k - 1] + np.sqrt(1 - rho * rho) * rng.standard_normal()
        r["balise"] = {"z": (e - e.mean()).tolist(), "c": [1.0 / np.sqrt(n)] * n, "info": 1.0,
                       "speed": rng.uniform(5, 25, n).tolist(),
                       "position": np.sort(rng.uniform(0, 6000, n)).tolist()}
    res = F.consensus(rows)
    assert [a["train"] for a in res.readers["alerts"]] == ["T0"], res.readers["alerts"]
    md = report_md(res, [], INFO, [])
    top = md[:md.index("## Map errors")]
    assert "**train T0's balise reader** is not the sensor its readings state: their errors " \
        "are correlated from one reading to the next" in top, top
    assert "its 20 runs pooled, 240 readings" in top, top


def test_a_train_without_an_alert_is_never_drawn_red():
    """Red (C3) marks a train with an alert and orange (C1) a section found by too few: the
    other trains' colours cycle through the rest."""
    from train_estimation.tools.fleet_report import train_color

    assert {train_color(i) for i in range(40)}.isdisjoint({"C3", "C1"})
    assert len({train_color(i) for i in range(8)}) == 8
