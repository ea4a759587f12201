"""Several passes tell a map error from a tunnel's drag: `diagnose` per pass, the fleet's test.

One pass cannot tell a gradient the map lacks from a tunnel's extra aerodynamic drag: both are a
force at one place. Over passes at different speeds they differ: a map error is the same
gradient at any speed, a drag ``c v^2`` reads as a gradient growing with the speed squared
(``core.offline.fleet.speed_test``). This benchmark simulates passes of metro_demo through one
stretch, at three cruise speeds (the driver's ``speed_margin`` below the line speed) and two
seeds each, with either a tunnel (``train_sim.unlisted.TunnelDrag``, not a listed cause) or a
map error (the true line steeper there: the ``gradient`` effect), runs `diagnose` on each pass's
measured bag, and prints what each pass found and the place-against-speed test over them.

    ./run bench passes --jobs 2            # 12 passes (about 4 min on two cores)
    ./run bench passes --quick --jobs 2    # 6 passes: one seed per speed (under 2 min)
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import math
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

from train_core.bagio import read_bag
from train_core.effects import GradientEffect
from train_core.model import load_line, load_train
from train_core.progress import track

from train_estimation.core.offline import fleet as FL
from train_estimation.core.offline.diagnose import diagnose
from train_estimation.core.offline.measured import MeasuredRun
from train_estimation.tools.fleet_dask import diagnosis_row
from train_sim.generate import generate
from train_sim.scenario import load_scenario
from train_sim.unlisted import TunnelDrag, Unlisted

STRETCH = (2000.0, 2700.0)  # m of metro_demo, run at cruise speed between two stations
TUNNEL_C = 12.0  # N/(m/s)^2: 1.7 per mille at 20 m/s for metro_b6
MAP_PERMILLE = 1.5  # the map's error there (the true line steeper)
MARGINS = (0.5, 5.0, 9.0)  # m/s below the line speed: cruise at about 21.7, 17 and 13 m/s


def one_pass(kind: str, margin: float, seed: int) -> dict:
    sc0 = load_scenario("metro_demo")
    sc = sc0.with_changes(duration=400.0, seed=seed,
                          driver=dataclasses.replace(sc0.driver, speed_margin=margin))
    if kind == "tunnel":
        sc = sc.with_changes(unlisted=Unlisted(tunnel_drag=TunnelDrag(*STRETCH, TUNNEL_C)))
    else:
        sc = sc.with_effects(dataclasses.replace(sc.effects,
                                                 gradient=GradientEffect(*STRETCH, MAP_PERMILLE)))
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "bag"
        generate(sc, path, measured=True)  # what the train sends: the inputs as received
        data = MeasuredRun.from_bag(read_bag(path))
    train = load_train(sc.train_path)
    dg = diagnose(data, load_line(sc.line_path), train)
    row = diagnosis_row(dg, train)
    return {"kind": kind, "margin": margin, "seed": seed, "cause": dg.cause,
            "start": row.get("gradient_start"), "end": row.get("gradient_end"),
            "permille": row.get("gradient_permille"), "se": row.get("gradient_se"),
            "v2": row.get("gradient_v2")}


def _timed_pass(run: tuple) -> dict:
    t0 = time.perf_counter()
    return {**one_pass(*run), "s": time.perf_counter() - t0}


def kind_passes(kind: str, seeds, alpha: float, jobs: int = 1
                ) -> tuple[list[dict], dict | None, bool]:
    """Every pass of ``kind`` (``tunnel`` or ``map error``) at the three cruise speeds and
    ``seeds`` (on ``jobs`` processes), the place-against-speed test over those that found the
    stretch (None: fewer than two), and whether it decided right (``speed`` for the tunnel,
    ``place`` for the map)."""
    runs = [(kind, m, s) for m in MARGINS for s in seeds]
    with contextlib.ExitStack() as stack:
        pool = stack.enter_context(ProcessPoolExecutor(max_workers=jobs)) if jobs > 1 else None
        rows = list(track(pool.map(_timed_pass, runs) if pool else map(_timed_pass, runs),
                          f"passes: {kind}", total=len(runs)))
    got = [r for r in rows if r["se"] is not None and r["v2"] is not None
           and r["permille"] is not None]
    t = FL.speed_test([r["permille"] for r in got], [r["se"] for r in got],
                      [r["v2"] for r in got], alpha)
    want = "speed" if kind == "tunnel" else "place"
    return rows, t, t is not None and t["decided"] == want


def report(kind: str, rows: list[dict], t: dict | None, ok: bool) -> str:
    """The passes of one kind as a markdown table, and the test's line."""
    want = "speed" if kind == "tunnel" else "place"
    md = [f"\n{kind} on [{STRETCH[0]:.0f}, {STRETCH[1]:.0f}) m of metro_demo "
          + (f"(extra drag {TUNNEL_C:g} v^2 N)" if kind == "tunnel" else
             f"(the true line {MAP_PERMILLE:+g} per mille steeper)"),
          "| cruise margin m/s | seed | diagnose | section m | per mille +- se | "
          "speed over it km/h | s |", "|---|---|---|---|---|---|---|"]
    for r in rows:
        found = r["se"] is not None and r["v2"] is not None and r["permille"] is not None
        where = f"[{r['start']:.0f}, {r['end']:.0f})" if found else "-"
        pm = f"{r['permille']:+.3f} +- {r['se']:.3f}" if found else "-"
        v = f"{3.6 * math.sqrt(r['v2']):.0f}" if found else "-"
        md.append(f"| {r['margin']:g} | {r['seed']} | {r['cause']} | {where} | {pm} | {v} | "
                  f"{r['s']:.0f} |")
    if t is None:
        md.append("place against speed: fewer than two passes found it -> FAIL")
    else:
        md.append(f"place against speed over {t['n']} passes at {3.6 * t['v_min']:.0f}-"
                  f"{3.6 * t['v_max']:.0f} km/h: p(the same at any speed) = "
                  f"{t['p_place']:.3g}, p(growing as v^2) = {t['p_speed']:.3g} -> "
                  f"{t['decided']} ({'PASS' if ok else 'FAIL'}: want {want})")
    return "\n".join(md)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="one seed per speed")
    ap.add_argument("--alpha", type=float, default=FL.FleetConfig().alpha,
                    help="the test's false-alarm rate (the fleet's alpha)")
    ap.add_argument("--jobs", type=int, default=1, help="parallel processes (default 1)")
    args = ap.parse_args(argv)
    seeds = (1,) if args.quick else (1, 2)
    ok = True
    for kind in ("tunnel", "map error"):
        rows, t, right = kind_passes(kind, seeds, args.alpha, args.jobs)
        print(report(kind, rows, t, right), flush=True)
        ok &= right
    print(f"\nRESULT: {'PASS' if ok else 'FAIL'}")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
