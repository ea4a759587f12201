#!/usr/bin/env python3
"""Benchmark of `diagnose` on generated measured bags, against the targets below.

    ./run bench diagnose --cases N [--seed S] [--jobs 1] [--sizes plain,subtle] [--pairs N]

Cases come from ``train_sim.cases.make_case`` (varied lines, trains, links, clocks and driving
styles; the hidden effect placed where the run exercises it): N per cause at each size, N with
no effect and N pairs of two different causes (plain size). Each case is simulated into a
measured bag (no ground truth) and the ``diagnose`` executable's entry point runs on it exactly
as a user would (--bag, --line, --train, --out); the report is then compared with the truth.

Printed (and written to benchmarks/out/diagnose.md, raw results to diagnose.json):
- confusion matrix per size: true cause (rows) against the reported cause (columns), and each
  cause's statuses (confirmed / not confirmed, with the reason / rejected);
- right cause confirmed, per size (target >= 97 % plain, >= 90 % subtle); nominal data with no
  confirmed cause (target >= 97 %; 1 - this is the false-alarm rate);
- pairs: both true causes confirmed and first and second in the ranking (target >= 90 %);
- effects outside the list (``--unlisted``): `unexplained` (target >= 80 %), a listed cause
  confirmed (target <= 10 %), the signature's phase right (target >= 80 %);
- main-parameter error |estimate - true| / |true - nominal| per cause (train_sim.cases
  main_error; the estimate is the true cause's entry in the ranking, whatever rank it has):
  median and the fraction within 0.2 (target: within 20 %);
- gain per cause where the cause was named: the report's before -> after (median) and the
  fraction of cases with a reduction >= 30 % (target for motion causes, held-out speed RMSE);
- time per bag (diagnose only, target < 10 s for a 10-minute bag on this 2-core machine);
- real lines (``--real N``, train_sim.real_lines: yizhuang_metro, zurich_stadelhofen, whole
  runs, where their TTOBench files are; a note says where to put an absent one): per line, N
  bags with a hidden gradient of 4-8 per mille over 300-700 m between two stops and N with no
  effect: the verdicts, the gradient confirmed, found where it is (overlap >= 75 %) and its
  size (error / true), and why it was not confirmed where it was not.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import os
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
OUT = os.path.join(HERE, "out")

from train_core.progress import Progress  # noqa: E402

from train_sim.cases import CAUSES, describe, main_error, make_case  # noqa: E402

MOTION = ("gradient", "resistance", "braking_rate", "brake_delay", "mass")
LABELS = CAUSES + ("none", "unexplained")
STATUSES = ("confirmed", "not confirmed", "rejected", "untestable")


def case_list(n: int, sizes, n_pairs: int, seed: int, n_nominal: int | None = None,
              n_unlisted: int = 0) -> list[dict]:
    """The case specifications (deterministic in seed): index -> (causes, size) or an unlisted
    effect (``unlisted``: its kind)."""
    from train_sim.unlisted_cases import KINDS

    specs = []
    for size in sizes:
        for c in CAUSES:
            specs += [{"causes": (c,), "size": size} for _ in range(n)]
    specs += [{"causes": (), "size": "plain"} for _ in range(n if n_nominal is None else n_nominal)]
    rng = np.random.default_rng([seed, 99])
    for _ in range(n_pairs):
        a, b = rng.choice(len(CAUSES), size=2, replace=False)
        specs.append({"causes": (CAUSES[a], CAUSES[b]), "size": "plain"})
    for kind in KINDS:
        specs += [{"causes": (), "size": "plain", "unlisted": kind} for _ in range(n_unlisted)]
    for i, s in enumerate(specs):
        s["index"], s["seed"] = i, seed
    return specs


def run_case(spec: dict) -> dict:
    """run_case_ with a crash recorded (reproduce: make_case(default_rng([seed, index])))."""
    try:
        return run_real_case(spec) if spec.get("real") else run_case_(spec)
    except Exception as exc:  # a crash is a result too: counted and listed, never hidden
        import traceback

        return {**spec, "causes": list(spec["causes"]), "rc": "crash", "time": 0.0,
                "duration": 0.0, "describe": f"seed [{spec['seed']}, {spec['index']}] "
                f"{'+'.join(spec['causes']) or 'none'} {spec['size']}",
                "error": f"{type(exc).__name__}: {exc} at "
                         f"{traceback.extract_tb(exc.__traceback__)[-1].name}"}


def real_specs(n: int, seed: int) -> tuple[list[dict], dict]:
    """The real-line cases (n hidden gradients and n nominal runs per line whose file is here)
    and {line: why it is skipped} for the others."""
    from train_sim.real_lines import available

    ok, missing = available()
    specs = [{"real": name, "causes": c, "size": "plain", "seed": seed, "index": 1000 + i}
             for name in ok for c in (("gradient",), ()) for i in range(n)]
    return specs, missing


def run_real_case(spec: dict) -> dict:
    """A real-line run (whole timetable), measured, diagnosed as a user runs the tool."""
    from train_estimation.tools import diagnose as tool
    from train_sim.generate import generate
    from train_sim.real_lines import available, hidden_gradient

    sc = available([spec["real"]])[0][spec["real"]]
    rng = np.random.default_rng([spec["seed"], spec["index"]])
    sc = sc.with_changes(seed=int(rng.integers(2**31)))
    out = {**spec, "causes": list(spec["causes"]), "duration": sc.duration,
           "describe": f"{spec['real']} {'+'.join(spec['causes']) or 'none'} seed "
                       f"[{spec['seed']}, {spec['index']}]"}
    if spec["causes"]:
        hg = hidden_gradient(sc, rng)
        sc = hg.scenario
        out["truth"] = {"start": hg.start, "end": hg.end, "permille": hg.permille}
    with tempfile.TemporaryDirectory(prefix="bench_diag_real_") as d:
        bag = os.path.join(d, "bag")
        generate(sc, bag, measured=True)
        t0 = time.perf_counter()
        with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
            rc = tool.main(["--bag", bag, "--line", sc.line_path, "--train", sc.train_path,
                            "--out", os.path.join(d, "diag"), "--quiet", "--no-plots"])
        out["time"], out["rc"] = time.perf_counter() - t0, rc
        if rc != 0:
            return out
        rep = json.load(open(os.path.join(d, "diag", "report.json")))
    out["reported"] = rep["cause"]
    out["confirmed"] = [r["cause"] for r in rep["ranking"] if r.get("status") == "confirmed"
                        and r["cause"] != "none"]
    g = next((r for r in rep["ranking"] if r["cause"] == "gradient"), None)
    out["gradient"] = g and {"status": g.get("status"), "why": g.get("why"),
                             **g.get("parameters", {})}
    out["unexplained"] = len(rep.get("unexplained") or [])
    return out


def real_table(results: list[dict], missing: dict) -> str:
    """Per real line: verdicts on hidden gradients and on nominal runs."""
    md = ["\n## Real lines (TTOBench tracks, whole runs)\n"]
    for name, why in missing.items():
        md.append(f"- {name}: skipped ({why})")
    if not results:
        return "\n".join(md) + "\n"
    md += ["| line | hidden | n | reported | gradient confirmed | found where it is (overlap "
           ">= 75 %) | size error / true (median) | time per bag (s) |",
           "|---|---|---|---|---|---|---|---|"]
    for name in sorted({r["real"] for r in results}):
        for causes in (["gradient"], []):
            sel = [r for r in results if r["real"] == name and r["causes"] == causes]
            ok = [r for r in sel if r.get("rc") == 0]
            if not sel:
                continue
            rep = ", ".join(f"{c} {sum(r['reported'] == c for r in ok)}"
                            for c in sorted({r["reported"] for r in ok}))
            conf = sum("gradient" in r["confirmed"] for r in ok)
            where, err = 0, []
            for r in ok:
                g, t = r.get("gradient"), r.get("truth")
                if not (g and t and "start" in g):
                    continue
                ov = min(g["end"], t["end"]) - max(g["start"], t["start"])
                if ov >= 0.75 * (t["end"] - t["start"]):
                    where += 1
                    err.append(abs(g["permille"] - t["permille"]) / abs(t["permille"]))
            md.append(f"| {name} | {'gradient' if causes else 'none'} | {len(sel)} | {rep} | "
                      f"{pct(conf, len(ok))}" + ("" if causes else " (false alarm)") + " | "
                      + (pct(where, len(ok)) if causes else "-") + " | "
                      + (f"{np.median(err):.2f}" if err else "-") + " | "
                      + (f"{np.mean([r['time'] for r in ok]):.1f}" if ok else "-") + " |")
    for r in results:
        g = r.get("gradient") or {}
        if r["causes"] and "gradient" not in r.get("confirmed", []):
            t = r["truth"]
            md.append(f"- {r['describe']}: hidden [{t['start']:.0f}, {t['end']:.0f}) "
                      f"{t['permille']:+.2f}; reported {r.get('reported')}; gradient "
                      f"{g.get('status')} [{g.get('start', 0):.0f}, {g.get('end', 0):.0f}) "
                      f"{g.get('permille', 0):+.2f}: {g.get('why')}")
        elif not r["causes"] and r.get("confirmed"):
            md.append(f"- {r['describe']}: false alarm, confirmed {r['confirmed']}")
    return "\n".join(md) + "\n"


def run_case_(spec: dict) -> dict:
    """Make the case, simulate the measured bag, run diagnose, score the report."""
    from train_core.bagio import read_bag

    from train_estimation.tools import diagnose as tool
    from train_sim.generate import generate
    from train_sim.unlisted_cases import unlisted_case

    rng = np.random.default_rng([spec["seed"], spec["index"]])
    if spec.get("unlisted"):
        uc = unlisted_case(rng, spec["unlisted"])
        case, scenario = uc.case, uc.scenario
        extra = {"phase": uc.phase, "truth": uc.truth}
    else:
        case = make_case(rng, spec["causes"] or None, spec["size"])
        scenario, extra = case.scenario, {}
    out = {**spec, **extra, "causes": list(spec["causes"]), "family": case.family,
           "describe": describe(case) + (f" + unlisted {spec['unlisted']}"
                                         if spec.get("unlisted") else ""),
           "duration": case.scenario.duration}
    with tempfile.TemporaryDirectory(prefix="bench_diag_") as d:
        paths = case.write(os.path.join(d, "case"))
        bag = os.path.join(d, "bag")
        generate(scenario, bag, measured=True)
        stamps = np.array([s for _, s, _ in read_bag(bag).topics["odometer"]])
        truth = case.truth_in_bag(float(stamps.min()), float(stamps.max()))
        t0 = time.perf_counter()
        buf_out, buf_err = io.StringIO(), io.StringIO()
        with contextlib.redirect_stdout(buf_out), contextlib.redirect_stderr(buf_err):
            rc = tool.main(["--bag", bag, "--line", str(paths["line"]), "--train",
                            str(paths["train"]), "--out", os.path.join(d, "diag"), "--quiet"])
        out["time"] = time.perf_counter() - t0
        out["rc"] = rc
        if rc != 0:
            out["error"] = buf_err.getvalue().strip()
            return out
        rep = json.load(open(os.path.join(d, "diag", "report.json")))
    out["reported"] = rep["cause"]
    out["ranking"] = [r["cause"] for r in rep["ranking"]]
    # a report without status (before the confirmation existed): accepted = the cause named
    out["status"] = {r["cause"]: r.get("status", "confirmed" if r["cause"] == rep["cause"]
                                       else "rejected") for r in rep["ranking"]}
    out["confirmed"] = [c for c in out["ranking"] if out["status"].get(c) == "confirmed"
                        and c != "none"]
    out["why"] = {r["cause"]: r["why"] for r in rep["ranking"] if r.get("why")}
    # what one run's data cannot tell each confirmed cause from (its checks' caveats)
    checks = rep["evidence"].get("_model", {}).get("confirmation", {}).get("checks", {})
    out["caveats"] = {c: checks[c]["caveat"] for c in out["confirmed"]
                      if checks.get(c, {}).get("caveat")}
    out["unexplained"] = rep.get("unexplained", [])
    out["untestable"] = [u["cause"] for u in rep["untestable"]]
    out["gain"] = rep.get("gain", {})
    out["errors"] = {}
    for c in case.causes:
        est = next((r["parameters"] for r in rep["ranking"] if r["cause"] == c), None)
        if est:
            try:
                out["errors"][c] = main_error(c, est, truth[c], case.nominal[c], case.v_ref)
            except (KeyError, ZeroDivisionError, TypeError):
                out["errors"][c] = None
    return out


# ------------------------------------------------------------------------------------------------
# Tables
# ------------------------------------------------------------------------------------------------

def pct(k, n):
    return f"{100.0 * k / n:.0f} % ({k}/{n})" if n else "-"


def tables(results: list[dict], sizes, args) -> str:
    md = []
    ok = [r for r in results if r.get("rc") == 0]
    failed = [r for r in results if r.get("rc") != 0]
    n_nom = args.cases if args.nominal is None else args.nominal
    md.append(f"# diagnose benchmark: {args.cases} case(s) per cause and size, {n_nom} "
              f"nominal, {args.pairs} pairs, seed {args.seed}\n")
    crashed = [r for r in failed if r.get("rc") == "crash"]
    md.append(f"{len(results)} bags, {len(failed) - len(crashed)} refused (exit != 0), "
              f"{len(crashed)} crashed.\n")
    short = {c: c[:6] for c in LABELS}
    for size in sizes:
        single = [r for r in ok if len(r["causes"]) == 1 and r["size"] == size]
        md.append(f"\n## Confusion matrix, {size} (rows: hidden cause, columns: reported)\n")
        md.append("| hidden \\ reported | " + " | ".join(short[c] for c in LABELS) + " | right |")
        md.append("|---" * (len(LABELS) + 2) + "|")
        right_all = 0
        for c in CAUSES:
            rows = [r for r in single if r["causes"][0] == c]
            cnt = [sum(r["reported"] == p for r in rows) for p in LABELS]
            right = sum(r["reported"] == c for r in rows)
            right_all += right
            md.append(f"| {c} | " + " | ".join(str(k) if k else "." for k in cnt)
                      + f" | {pct(right, len(rows))} |")
        target = 97 if size == "plain" else 90
        md.append(f"\nright cause (confirmed), {size}: **{pct(right_all, len(single))}** "
                  f"(target >= {target} %)\n")
        md.append(status_table(single, size))
    nominal = [r for r in ok if not r["causes"] and not r.get("unlisted")]
    conf = [r for r in nominal if r["confirmed"]]
    n_unexp = sum(r["reported"] == "unexplained" for r in nominal)
    md.append(f"\nnominal data, no confirmed cause: **{pct(len(nominal) - len(conf), len(nominal))}"
              f"** (target >= 97 %); false-alarm rate {pct(len(conf), len(nominal))}; false "
              "alarms: " + (", ".join(sorted({c for r in conf for c in r["confirmed"]}))
                            or "none") + f"; `none` reported: "
              f"{pct(sum(r['reported'] == 'none' for r in nominal), len(nominal))}, "
              f"`unexplained`: {pct(n_unexp, len(nominal))}\n")
    pairs = [r for r in ok if len(r["causes"]) == 2]
    top2 = sum(set(r["ranking"][:2]) == set(r["causes"])
               and set(r["causes"]) <= set(r["confirmed"]) for r in pairs)
    md.append(f"\npairs, both causes confirmed and first and second: **{pct(top2, len(pairs))}** "
              f"(target >= 90 %)\n")
    for r in pairs:
        md.append(f"- {'+'.join(r['causes'])}: ranking {', '.join(r['ranking'][:3])}")
    md.append(unlisted_table([r for r in ok if r.get("unlisted")]))
    md.append("\n## Main parameter and gain per cause (single-cause bags)\n")
    md.append("main-parameter error = |estimate - true| / |true - nominal| (train_sim.cases."
              "main_error; estimate: the true cause's entry in the ranking). gain: the report's "
              "before -> after where the cause was named.\n")
    md.append("| cause | size | n | error median | error <= 0.2 | gain metric | before -> after "
              "(median) | reduction >= 30 % |")
    md.append("|---|---|---|---|---|---|---|---|")
    for c in CAUSES:
        for size in sizes:
            rows = [r for r in ok if r["causes"] == [c] and r["size"] == size]
            errs = [r["errors"].get(c) for r in rows if r["errors"].get(c) is not None]
            named = [r for r in rows if r["reported"] == c and r["gain"].get("before")
                     is not None and r["gain"].get("after") is not None]
            b = [r["gain"]["before"] for r in named]
            a = [r["gain"]["after"] for r in named]
            higher_better = bool(named) and "likelihood" in named[0]["gain"].get("metric", "")
            if higher_better:  # log-likelihood per sample: better = higher (no 30 % target)
                red = [r for r in named if r["gain"]["after"] > r["gain"]["before"]]
            else:
                red = [r for r in named if r["gain"]["before"] > 0
                       and 1 - r["gain"]["after"] / r["gain"]["before"] >= 0.3]
            metric = named[0]["gain"].get("metric", "")[:40] if named else "-"
            md.append(f"| {c} | {size} | {len(rows)} | "
                      + (f"{np.median(errs):.2f}" if errs else "-") + " | "
                      + pct(sum(e <= 0.2 for e in errs), len(errs)) + f" | {metric} | "
                      + (f"{np.median(b):.3g} -> {np.median(a):.3g}" if named else "-") + " | "
                      + pct(len(red), len(named)) + (" (higher is better: improved)"
                                                     if higher_better else "") + " |")
    t = np.array([r["time"] for r in ok])
    d = np.array([r["duration"] for r in ok])
    if t.size:
        md.append(f"\ntime per bag (diagnose only, {args.jobs} job(s) on this machine): mean "
                  f"{t.mean():.1f} s, median {np.median(t):.1f} s, max {t.max():.1f} s; per 10 "
                  f"minutes of data: {np.mean(t / d * 600):.1f} s (target < 10 s)\n")
    if failed:
        md.append("\n## Refused or crashed bags\n")
        for r in failed:
            md.append(f"- {r['describe']}: {r.get('error', '')[:200]}")
    return "\n".join(md) + "\n"


def status_table(single: list[dict], size: str) -> str:
    """The hidden cause's own status in the ranking (untestable: in the report's untestable)."""
    md = [f"\nstatus of the hidden cause, {size}:\n",
          "| hidden | " + " | ".join(STATUSES) + " |", "|---" * (len(STATUSES) + 1) + "|"]
    for c in CAUSES:
        rows = [r for r in single if r["causes"][0] == c]
        if not rows:
            continue
        st = ["untestable" if c in r["untestable"] else r["status"].get(c, "-") for r in rows]
        md.append(f"| {c} | " + " | ".join(str(st.count(s)) if st.count(s) else "."
                                           for s in STATUSES) + " |")
    return "\n".join(md) + "\n"


def unlisted_table(rows: list[dict]) -> str:
    """Effects outside the list: the verdict, a listed cause confirmed, the signature's phase."""
    if not rows:
        return ""
    md = ["\n## Effects outside the list (train_sim.unlisted_cases)\n",
          "| effect | n | `unexplained` | no listed cause confirmed | listed cause confirmed "
          "| phase right | reported |", "|---|---|---|---|---|---|---|"]
    kinds = sorted({r["unlisted"] for r in rows})
    for k in kinds + [None]:
        sel = [r for r in rows if k is None or r["unlisted"] == k]
        n = len(sel)
        unexp = sum(r["reported"] == "unexplained" for r in sel)
        conf = sum(bool(r["confirmed"]) for r in sel)
        phase = sum(bool(r["unexplained"]) and r["unexplained"][0].get("phase") == r["phase"]
                    for r in sel)
        rep = ", ".join(f"{c} {sum(r['reported'] == c for r in sel)}"
                        for c in sorted({r["reported"] for r in sel}))
        md.append(f"| {k or '**all**'} | {n} | {pct(unexp, n)} | {pct(n - conf, n)} | "
                  f"{pct(conf, n)} | {pct(phase, n)} | {rep} |")
    md.append("\ntargets: `unexplained` (no listed cause confirmed) >= 80 %, a listed cause "
              "confirmed <= 10 %, the signature's phase right >= 80 % (first entry of "
              "`unexplained`; true phase: tunnel_drag all, brake_fade braking, traction_gain "
              "traction, wind all)\n")
    for r in rows:
        u = r["unexplained"][0] if r["unexplained"] else {}
        md.append(f"- {r['describe']}: {r['reported']}; confirmed {r['confirmed'] or '-'}; "
                  f"phase {u.get('phase', '-')} (true {r['phase']}), where {u.get('where')}, "
                  f"when {u.get('when')}, speed {u.get('speed')}")
        for c, told in (r.get("caveats") or {}).items():
            md.append(f"  - {c}: {told}")
    return "\n".join(md) + "\n"


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="bench_diagnose", description=__doc__.splitlines()[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter,
                                epilog="\n".join(__doc__.splitlines()[2:]))
    p.add_argument("--cases", type=int, default=2, help="cases per cause and size (default 2)")
    p.add_argument("--pairs", type=int, default=None, help="pairs (default: --cases x 3)")
    p.add_argument("--seed", type=int, default=0, help="seed of every case (default 0)")
    p.add_argument("--jobs", type=int, default=1, help="parallel processes (default 1)")
    p.add_argument("--sizes", default="plain,subtle",
                   help="sizes (default plain,subtle; '' for no single-cause bags)")
    p.add_argument("--nominal", type=int, default=None,
                   help="bags with no effect (default: --cases), e.g. --sizes '' --pairs 0 "
                        "--nominal 40 for the false-alarm rate alone")
    p.add_argument("--unlisted", type=int, default=0,
                   help="bags per effect outside the list (train_sim.unlisted_cases: "
                        "tunnel_drag, brake_fade, traction_gain, wind; default 0)")
    p.add_argument("--real", type=int, default=1,
                   help="bags with a hidden gradient and bags with no effect per real line "
                        "whose TTOBench file is here (default 1; 0 for none)")
    p.add_argument("--name", default="diagnose",
                   help="output files benchmarks/out/NAME.md and NAME.json (default diagnose)")
    p.add_argument("--quick", action="store_true",
                   help="under a minute: one plain case per cause, one pair, one nominal bag, no "
                        "real line, 2 processes, output NAME diagnose_quick (each option given "
                        "overrides)")
    if p.parse_known_args(argv)[0].quick:  # the quick values as defaults: given ones win
        p.set_defaults(cases=1, sizes="plain", pairs=1, nominal=1, real=0, jobs=2,
                       name="diagnose_quick")
    args = p.parse_args(argv)
    if args.pairs is None:
        args.pairs = 3 * args.cases
    sizes = [s for s in args.sizes.split(",") if s]
    specs = case_list(args.cases, sizes, args.pairs, args.seed, args.nominal,
                      args.unlisted)
    real, missing = real_specs(args.real, args.seed) if args.real > 0 else ([], {})
    for name, why in missing.items():
        print(f"note: real line {name} skipped: {why}")
    specs += real
    prog = Progress("bench diagnose")

    def bar(done: int, what: str = "") -> None:
        prog(done, len(specs), what)

    results = []
    bar(0)
    if args.jobs <= 1:
        for s in specs:
            results.append(run_case(s))
            bar(len(results), f"{'+'.join(s['causes']) or 'none'} {s['size']}")
    else:
        with ProcessPoolExecutor(max_workers=args.jobs) as ex:
            for r in ex.map(run_case, specs):
                results.append(r)
                bar(len(results), f"{'+'.join(r['causes']) or 'none'} {r['size']}")
    synthetic = [r for r in results if not r.get("real")]
    md = tables(synthetic, sizes, args) if synthetic or not real else ""
    if args.real > 0:
        md += real_table([r for r in results if r.get("real")], missing)
    print(md)
    os.makedirs(OUT, exist_ok=True)
    with open(os.path.join(OUT, f"{args.name}.md"), "w") as f:
        f.write(md)
    with open(os.path.join(OUT, f"{args.name}.json"), "w") as f:
        json.dump(results, f, indent=1, default=str)
    print(f"wrote {os.path.join(OUT, args.name + '.md')} and {args.name}.json")
    return 0


if __name__ == "__main__":
    sys.exit(main())
