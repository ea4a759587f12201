#!/usr/bin/env python3
"""Power of `diagnose`'s held-out check per cause: how often it confirms a true effect, and how
often it confirms one that is not there.

    ./run bench heldout --quick            # 2 seeds per cause and size, 4 nominal: < 2 min
    ./run bench heldout --cases 10 --nominal 10 --jobs 1

The held-out check (docs/diagnose.md, "Confirm before naming", check 1) on its own, without the
search before it: for each cause at its plain and subtle sizes (``train_sim.cases.make_case``,
seeded: case i of seed S is ``default_rng([S, i])``), the measured bag is simulated, the cause
is fitted against the believed model (with its command-time offset) at the noise of the model
that includes it, as the search accepts a cause, and the check runs as ``confirm`` runs it
(``confirm.heldout_motion`` with the cause's own blocks, and its halves test: the folds'
fits agree; the clock and the link: ``confirm.heldout_own``). *Power* is the fraction of bags
with the effect where it confirms. ``--tables benchmarks/out/NAME.json`` prints a run's
tables again as the checks are now (a cause whose halves test was dropped since).

*False*: the same for every cause on bags with no effect (``none``: the rate at which the check
confirms a cause that is not there; a one-sided test at Z > 2 gives at most 2.3 %) and, with
``--cross``, on the single-cause bags for every other cause (a cause that is not there but
another is: a listed cause can fit part of another, which the checks after this one separate).

Pairs (``--pairs N``): two causes in the bag, each checked with the other fitted in the model
(``others``), as ``confirm`` checks causes confirmed together: both confirmed.
"""

from __future__ import annotations

import argparse
import contextlib
import copy
import io
import json
import os
import sys
import tempfile
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
OUT = os.path.join(HERE, "out")

from bench_diagnose import pct, run_specs  # noqa: E402

from train_sim.cases import CAUSES, make_case  # noqa: E402


def case_list(n: int, sizes, n_nominal: int, n_pairs: int, seed: int) -> list[dict]:
    specs = []
    for size in sizes:
        for c in CAUSES:
            specs += [{"causes": (c,), "size": size} for _ in range(n)]
    specs += [{"causes": (), "size": "plain"} for _ in range(n_nominal)]
    rng = np.random.default_rng([seed, 98])
    for _ in range(n_pairs):
        a, b = rng.choice(len(CAUSES), size=2, replace=False)
        specs.append({"causes": (CAUSES[a], CAUSES[b]), "size": "plain"})
    for i, s in enumerate(specs):
        s["index"], s["seed"] = i, seed
    return specs


def analysis(bag, line, train):
    """(Motion, DiagConfig, own likelihoods, null with the command-time offset) of a bag."""
    from train_core.model import load_line, load_train

    from train_estimation.core.offline.diagnose.causes import REGISTRY
    from train_estimation.core.offline.diagnose.motion import Motion
    from train_estimation.core.offline.diagnose.run import DiagConfig, prepare
    from train_estimation.core.offline.diagnose.stage import Null, Stage
    from train_estimation.tools.diagnose import read_measured

    cfg = DiagConfig()
    line, train = load_line(line), load_train(train)
    run = prepare(read_measured(bag), line, cfg, train)
    own = {c.name: r for c in REGISTRY if (r := c.own_test(run)) is not None}
    mo = Motion(run, line, train, cfg)
    st0 = Stage(mo, Null(), cfg)
    shift = st0.nuisance_shift()[0]
    return mo, cfg, own, Null(shift=shift)


def fitted(mo, cfg, null, name: str, own: dict):
    """The cause ``name`` fitted against ``null`` and refitted at the noise of the model that
    includes it (as the search accepts a cause): (CauseFit, noise)."""
    from train_estimation.core.offline.diagnose.causes import BY_NAME
    from train_estimation.core.offline.diagnose.search import refit_at_own_noise
    from train_estimation.core.offline.diagnose.stage import Stage

    cause = BY_NAME[name]
    st = Stage(mo, null, cfg)
    if not cause.in_motion_model:
        return cause.score(st, own.get(name), 0.0), (st.q, st.r_s)
    fit = cause.score(st, None, st.null_ll())
    fit.noise = (st.q, st.r_s)
    refit_at_own_noise(mo, null, cause, fit, cfg)
    return fit, fit.noise


def held_out(mo, cfg, own, null, name: str, others: list | None = None) -> dict:
    """The held-out check of cause ``name`` against ``null`` extended by the fits ``others``
    (each fitted with the rest in the model, then this one with them): {ok, z, gain}."""
    from train_estimation.core.offline.diagnose.causes import BY_NAME

    cause = BY_NAME[name]
    out = held_out_(mo, cfg, own, null, name, others)
    if "fit" in out:
        out["resolved"] = cause.resolution(out["fit"], mo) is None
    return out


def held_out_(mo, cfg, own, null, name: str, others: list | None = None) -> dict:
    from train_estimation.core.offline.diagnose.causes import BY_NAME
    from train_estimation.core.offline.diagnose.confirm import (
        CONFIRM,
        heldout_motion,
        heldout_own,
        place_block,
    )
    from train_estimation.core.offline.diagnose.gain import GainContext
    from train_estimation.core.offline.diagnose.stage import Stage

    cause = BY_NAME[name]
    base = copy.deepcopy(null)
    for f in others or []:
        BY_NAME[f.cause].extend_null(base, f, mo)
    if cause.untestable(mo.run, cfg, own.get(name)) is not None:
        return {"ok": False, "untestable": True}
    try:
        fit, noise = fitted(mo, cfg, base, name, own)
    except (KeyError, IndexError, ValueError) as exc:
        return {"ok": False, "error": str(exc)}
    if not cause.in_motion_model:
        if name not in own:
            return {"ok": False, "untestable": True}
        ctx = GainContext(mo, Stage(mo, base, cfg), cfg, own)
        h = heldout_own(cause, fit, ctx)
        halves = h.get("halves", {})
        return {"ok": bool(h["ok"] and halves.get("consistent", True)), "held": bool(h["ok"]),
                "halves": halves, "z": None, "gain": None, "fit": fit}
    h = heldout_motion(mo, base, cause, cfg, noise, CONFIRM, place_block(mo, cause, fit, cfg),
                       cause.nominal(mo), fit)
    halves = h.get("halves", {})
    return {"ok": bool(h["ok"] and halves.get("consistent", True)), "held": bool(h["ok"]),
            "halves": halves, "z": h["z"], "gain": h["gain_loglik"], "fit": fit,
            "folds": h["fitted_on_folds"]}


def run_case(spec: dict) -> dict:
    try:
        return run_case_(spec)
    except Exception as exc:  # a crash is a result too: counted, never hidden
        return {**spec, "causes": list(spec["causes"]), "rc": "crash",
                "error": f"{type(exc).__name__}: {exc}"}


def run_case_(spec: dict) -> dict:
    from train_estimation.core.offline.diagnose.causes import BY_NAME
    from train_sim.generate import generate

    rng = np.random.default_rng([spec["seed"], spec["index"]])
    case = make_case(rng, spec["causes"] or None, spec["size"])
    out = {**spec, "causes": list(spec["causes"]), "family": case.family, "rc": 0,
           # how the bag records its commands: the simulator publishes the driver's current
           # target at each odometer sample (Hz, and the driver's cycle s)
           "recording": [case.scenario.odometer_rate, case.scenario.driver.control_period]}
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="bench_held_") as d:
        paths = case.write(os.path.join(d, "case"))
        bag = os.path.join(d, "bag")
        with contextlib.redirect_stdout(io.StringIO()):
            generate(case.scenario, bag, measured=True)
        mo, cfg, own, null = analysis(bag, paths["line"], paths["train"])
    test = list(CAUSES) if (not spec["causes"] or spec.get("cross")) else list(spec["causes"])
    res = {}
    if len(spec["causes"]) == 2:
        a, b = spec["causes"]
        fa = held_out(mo, cfg, own, null, a).get("fit")
        fb = held_out(mo, cfg, own, null, b).get("fit")
        for x, other in ((a, fb), (b, fa)):
            oth = [other] if other is not None and BY_NAME[other.cause].in_motion_model \
                else []
            r = held_out(mo, cfg, own, null, x, oth)
            res[x] = {k: v for k, v in r.items() if k not in ("fit", "folds")}
    else:
        for c in test:
            r = held_out(mo, cfg, own, null, c)
            res[c] = {k: v for k, v in r.items() if k not in ("fit",)}
    out["held"] = res
    out["time"] = time.perf_counter() - t0
    return out


def _confirms(h: dict, cause: str) -> bool:
    """The check confirms: the held-out score test passes and, for a cause that has the
    halves test now (``Cause.halves``), the folds' fits agree (results written before a
    cause's halves test was dropped are read as the check is now)."""
    from train_estimation.core.offline.diagnose.causes import BY_NAME

    if "held" not in h:
        return bool(h.get("ok"))
    return bool(h["held"] and (not BY_NAME[cause].halves
                               or h.get("halves", {}).get("consistent", True)))


def _disagree(h: dict, cause: str) -> bool:
    from train_estimation.core.offline.diagnose.causes import BY_NAME

    return bool(BY_NAME[cause].halves) and not h.get("halves", {}).get("consistent", True)


def figures(results: list[dict]) -> dict:
    """The counts the tables show, the checks read as they are now (``_confirms``): per cause
    {"plain", "subtle": power (k, n), "nominal": false confirmations on bags with no effect
    (k, n), "resolved": of those, beyond the cause's resolution (k), "other": on the bags of
    another cause (k, n), "z": the plain bags' Z, "halves": true causes whose folds' fits
    disagree (k, n)}, and "pairs": both confirmed (k, n)."""
    ok = [r for r in results if r.get("rc") == 0]
    for r in ok:
        for c, h in r["held"].items():
            h["ok"] = _confirms(h, c)
    nominal = [r for r in ok if not r["causes"]]
    out = {}
    for c in CAUSES:
        f = {}
        for size in ("plain", "subtle"):
            rows = [r for r in ok if r["causes"] == [c] and r["size"] == size]
            f[size] = (sum(r["held"][c]["ok"] for r in rows), len(rows))
        held = [r["held"][c] for r in nominal if c in r["held"]]
        f["nominal"] = (sum(h["ok"] for h in held), len(held))
        f["resolved"] = sum(h["ok"] and h.get("resolved", False) for h in held)
        fo = [r["held"][c]["ok"] for r in ok if len(r["causes"]) == 1 and r["causes"] != [c]
              and c in r["held"]]
        f["other"] = (sum(fo), len(fo))
        f["z"] = [r["held"][c].get("z") for r in ok if r["causes"] == [c]
                  and r["size"] == "plain" and r["held"][c].get("z") is not None]
        hv = [_disagree(r["held"][c], c) for r in ok if r["causes"] == [c]]
        f["halves"] = (sum(hv), len(hv))
        f["halves_z"] = [abs(q["z"]) for r in ok if r["causes"] == [c]
                         for q in (r["held"][c].get("halves", {}).get("quantities") or {}
                                   ).values() if q.get("z") is not None]
        out[c] = f
    pairs = [r for r in ok if len(r["causes"]) == 2]
    out["pairs"] = (sum(all(r["held"][c]["ok"] for c in r["causes"]) for r in pairs), len(pairs))
    return out


def _zs(z: list) -> str:
    """The halves' |z| of the true causes: median, max and how many beyond 1.96."""
    if not z:
        return "-"
    return (f"{np.median(z):.2f}, {max(z):.2f}, "
            f"{sum(x > 1.96 for x in z)}/{len(z)}")


BY_RECORDING = ("traction_delay", "brake_delay", "gradient", "adhesion_section")


def _by_recording(ok: list[dict]) -> list[str]:
    """The nominal bags' Z per cause of :data:`BY_RECORDING`, by how the bag records its
    commands (odometer rate, driver's cycle): a 5 Hz odometer beside a 0.1 s driver stamps
    every other command change 0.1 s late, and a score whose SD is not 1 shows it
    (docs/benchmarks.md, "The delays' excess")."""
    groups: dict = {}
    counts: dict = {}  # bags per recording
    for r in ok:
        if r["causes"] or not r.get("recording"):
            continue
        key = tuple(r["recording"])
        g = groups.setdefault(key, {c: [] for c in BY_RECORDING})
        counts[key] = counts.get(key, 0) + 1
        for c in BY_RECORDING:
            z = (r["held"].get(c) or {}).get("z")
            if z is not None:
                g[c].append(z)
    if not groups:
        return []
    md = ["\nZ on the nominal bags by how they record their commands (the odometer's rate, "
          "the driver's cycle): mean, SD, how many above 2 (of a standard normal: 0, 1, "
          "2.3 %)\n", "| odometer Hz, driver s | bags | " + " | ".join(BY_RECORDING) + " |",
          "|---|---|" + "---|" * len(BY_RECORDING)]
    for key in sorted(groups):
        g = groups[key]
        md.append(f"| {key[0]:g}, {key[1]:g} | {counts[key]} | " + " | ".join(
            f"{np.mean(v):+.2f}, {np.std(v):.2f}, {sum(z > 2 for z in v)}" if v else "-"
            for v in g.values()) + " |")
    return md


def tables(results: list[dict], sizes, args) -> str:
    ok = [r for r in results if r.get("rc") == 0]
    fig = figures(results)
    md = [f"# held-out check: {args.cases} bag(s) per cause and size, {args.nominal} nominal, "
          f"{args.pairs} pairs, seed {args.seed}\n",
          f"{len(results)} bags, {len(results) - len(ok)} crashed.\n",
          "power: the held-out score test passes and the folds' fits agree (halves); "
          "halves: bags with the cause where the folds' fits disagree.\n",
          "false, nominal: bags with no effect where it confirms the cause (in brackets: where "
          "the fit is also beyond the cause's resolution, check 2, as a confirmation needs).\n",
          "| cause | power, plain | power, subtle | false, nominal | false, other cause | "
          "Z plain (median) | halves disagree (true cause) | halves \\|z\\| (true cause): "
          "median, max, > 1.96 |", "|---|---|---|---|---|---|---|---|"]
    for c in CAUSES:
        f = fig[c]
        cells = [pct(*f[size]) if size in sizes else "-" for size in ("plain", "subtle")]
        md.append(f"| {c} | {cells[0]} | {cells[1]} | {pct(*f['nominal'])} ({f['resolved']}) | "
                  f"{pct(*f['other']) if args.cross else '-'} | "
                  + (f"{np.median(f['z']):.1f}" if f["z"] else "-")
                  + f" | {pct(*f['halves'])} | " + _zs(f["halves_z"]) + " |")
    md += _by_recording(ok)
    pairs = [r for r in ok if len(r["causes"]) == 2]
    if pairs:
        md.append(f"\npairs, each held out with the other in the model, both confirmed: "
                  f"**{pct(*fig['pairs'])}**\n")
        for r in pairs:
            md.append(f"- {' + '.join(r['causes'])} ({r['family']}): " + ", ".join(
                f"{c} {'ok' if r['held'][c]['ok'] else 'failed'}"
                + (f" Z {r['held'][c]['z']:.1f}" if r["held"][c].get("z") is not None else "")
                for c in r["causes"]))
    misses = [(r, c) for r in ok for c in r["causes"] if len(r["causes"]) == 1
              and not r["held"][c]["ok"]]
    if misses:
        md.append("\nmisses (true cause not confirmed by the held-out check):\n")
        for r, c in misses:
            h = r["held"][c]
            md.append(f"- seed [{r['seed']}, {r['index']}] {c} {r['size']} ({r['family']}): "
                      + (f"Z {h['z']:.2f}, gain {h['gain']:+.3g}" if h.get("z") is not None
                         else str({k: v for k, v in h.items() if k != "folds"}))
                      + (f"; {h['halves']['why']}" if h.get("halves", {}).get("why") else ""))
    t = [r["time"] for r in ok]
    if t:
        md.append(f"\ntime per bag (simulation and checks): mean {np.mean(t):.1f} s\n")
    return "\n".join(md) + "\n"


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="bench_heldout", description=__doc__.splitlines()[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter,
                                epilog="\n".join(__doc__.splitlines()[2:]))
    p.add_argument("--cases", type=int, default=10, help="bags per cause and size (default 10)")
    p.add_argument("--nominal", type=int, default=10, help="bags with no effect (default 10)")
    p.add_argument("--pairs", type=int, default=0, help="bags with two causes (default 0)")
    p.add_argument("--seed", type=int, default=0, help="seed of every case (default 0)")
    p.add_argument("--sizes", default="plain,subtle", help="sizes (default plain,subtle)")
    p.add_argument("--cross", action="store_true",
                   help="check every other cause on the single-cause bags too (slower)")
    p.add_argument("--causes", default=",".join(CAUSES), help="causes (default: all)")
    p.add_argument("--jobs", type=int, default=1, help="parallel processes (default 1)")
    p.add_argument("--quick", action="store_true",
                   help="2 bags per cause, plain only, 4 nominal (under 2 min)")
    p.add_argument("--name", default="heldout", help="output benchmarks/out/NAME.md, .json")
    p.add_argument("--tables", metavar="JSON",
                   help="print the tables of a run's results (benchmarks/out/NAME.json) again, "
                        "as the checks are now, and exit")
    args = p.parse_args(argv)
    if args.tables:
        results = json.load(open(args.tables))
        first = results[0] if results else {}
        args.seed = first.get("seed", args.seed)
        args.cases = max(sum(r["causes"] == [c] and r["size"] == "plain" for r in results)
                         for c in CAUSES)
        args.nominal = sum(not r["causes"] for r in results)
        args.pairs = sum(len(r["causes"]) == 2 for r in results)
        args.cross = any(r.get("cross") for r in results)
        print(tables(results, sorted({r["size"] for r in results if r["causes"]}), args))
        return 0
    if args.quick:
        args.cases, args.nominal, args.sizes = 1, 2, "plain"
    sizes = [s for s in args.sizes.split(",") if s]
    chosen = set(args.causes.split(","))
    specs = [s for s in case_list(args.cases, sizes, args.nominal, args.pairs, args.seed)
             if not s["causes"] or len(s["causes"]) == 2 or s["causes"][0] in chosen]
    for s in specs:
        s["cross"] = args.cross
    results = run_specs(run_case, specs, args.jobs, "bench heldout")
    md = tables(results, sizes, args)
    print(md)
    os.makedirs(OUT, exist_ok=True)
    with open(os.path.join(OUT, f"{args.name}.md"), "w") as f:
        f.write(md)
    with open(os.path.join(OUT, f"{args.name}.json"), "w") as f:
        json.dump(results, f, indent=1, default=str)
    return 0


if __name__ == "__main__":
    sys.exit(main())
