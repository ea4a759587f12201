#!/usr/bin/env python3
"""Benchmark of the Wen et al. (2017) robust filter and its baselines on simulated runs.

Prints markdown tables (and writes PNGs to benchmarks/out/):

1. Wen Table III side by side on ``wen2017_subway`` (R = diag{1, 0.01}, q = 0.49 N^2,
   alpha-bar = 0.875): per-seed statistical variance of the position / velocity error, mean and
   95 % interval (2.5 / 97.5 percentiles over seeds), and ratios to FOH.
2. Theorem 2's bound: per step, Monte Carlo MSE over seeds vs the mean bound Sigma(k|k).
3. Sweeps (received fraction 1.0 .. 0.3; v^2 coefficient of the true train -50 % .. +50 %):
   RMSE per filter.
4. ETCS yardstick on ``metro_demo``: 95th percentile of |position error| vs SUBSET-041's
   +-(5 m + 5 % of the distance since the last balise).
5. Core step time of the robust filter (predict + update of one odometer period), median / p99.

Usage::

    python3 benchmarks/bench_robust_filter.py               # full size (100 seeds)
    python3 benchmarks/bench_robust_filter.py --quick       # a few seeds, for development
    python3 benchmarks/bench_robust_filter.py --seeds 30 --etcs-seeds 5 --sweep-seeds 10

Filters (rows):
  foh           direct measurements with first-order hold (the paper's comparison)
  robust_eq24   eq. (21)-(24) literally: Eu = I (lambda_bar = |x^|^2), gain (24) with abar
  robust        Eu = I, corrected gain (the minimiser of tr (22)); gamma, eps chosen per step
  robust_vel    Eu = [0 1] (only v enters the uncertainty), corrected gain
  kf            Kalman filter with intermittent observations, same nominal model; process noise
                Q = (q + (c v_max^2/2)^2/3) E E^T: the v^2 uncertainty as a white force
  oracle        EKF on the true train / line / actuator at 50 ms internal steps, known noises
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
from train_core.progress import track  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
for _p in (ROOT / "ros_ws/src/train_sim", ROOT / "ros_ws/src/train_estimation"):
    if str(_p) not in sys.path:
        sys.path.insert(0, str(_p))

from train_core.effects import Effects, ResistanceEffect  # noqa: E402
from train_core.link import LinkParams  # noqa: E402

from train_estimation.core.robust.filter_base import filter_params_from_train  # noqa: E402
from train_estimation.core.robust.robust_filter import (  # noqa: E402
    BaliseReading,
    FOHFilter,
    IntermittentKF,
    OdometerReading,
    RobustFilter,
)
from train_estimation.core.robust.wen_model import WenModel  # noqa: E402
from train_sim.scenario import load_scenario  # noqa: E402
from train_sim.world import simulate  # noqa: E402

ALL = ("foh", "robust_eq24", "robust", "robust_vel", "kf", "oracle")
ROBUST = ("robust_eq24", "robust", "robust_vel")
Q_WIND = 0.49  # N^2, Wen Sec. IV q_k
ORACLE_ACCEL_PSD = 1e-6  # (m/s^2)^2/Hz: covers RK4-vs-ZOH residue, the world has no noise


def make_filters(sc, names, alpha_bar, q=Q_WIND, use_distance=True, epsilon=None):
    """Filters of the requested ``names`` for scenario ``sc`` (believed models only, except
    the oracle, which gets the true train, line and actuator)."""
    tr, ln = sc.train, sc.line
    x0 = np.array([sc.start_position, sc.start_speed])
    P0 = np.diag([tr.odometer_distance_std ** 2 or 1.0, tr.odometer_speed_variance])
    base = filter_params_from_train(tr, alpha_bar=alpha_bar, epsilon=epsilon,
                                    use_distance=use_distance,
                                    odometer_origin=sc.start_position, gate=8.0,
                                    max_dt=max(1.0 / sc.odometer_rate, 0.1))
    out = {}
    for n in names:
        if n == "foh":
            out[n] = FOHFilter(WenModel.from_params(tr, ln, q), base, x0, 0.0)
        elif n in ROBUST:
            unc = "velocity" if n == "robust_vel" else "paper"
            p = replace(base, gain="paper" if n == "robust_eq24" else "corrected")
            out[n] = RobustFilter(WenModel.from_params(tr, ln, q, uncertainty=unc), p, x0, P0,
                                  0.0, brake=tr.brake)
        elif n == "kf":
            # The same model; the norm-bounded v^2 term |c dv v| <= c v_max^2 / 2 (eq. (8))
            # treated as a white force, uniform over its bound: variance (c v_max^2 / 2)^2 / 3.
            # (With Q = q E E^T alone, q = 0.49 N^2, the KF trusts the nominal model, drifts by
            # tens of metres on metro_demo and then gates every reading out.)
            m = WenModel.from_params(tr, ln, q)
            p = replace(base, kf_q=q + (tr.davis.c * m.v_max ** 2 / 2) ** 2 / 3)
            out[n] = IntermittentKF(m, p, x0, P0, 0.0, brake=tr.brake)
        elif n == "oracle":
            tt = sc.true_train
            m = replace(WenModel.from_params(tt, sc.true_line, 0.0),
                        control_mass=tr.effective_mass)  # drive force planned for the believed
            p = replace(base, max_dt=0.05, kf_q=0.0)
            out[n] = IntermittentKF(m, p, x0, P0, 0.0, brake=tt.brake, ekf=True,
                                    accel_psd=ORACLE_ACCEL_PSD)
        else:
            raise ValueError(n)
    return out


def run(sc, res, filters, time_filter=None):
    """Feed one simulated run to the filters in time order.

    Per odometer period k: received balise readings with stamps in (t_{k-1}, t_k], then the
    odometer slot k (received or lost), then the control command issued at t_k. Returns
    estimates (K, 2), covariances (K, 2, 2) per filter, the truth (K, 2), the distance since the
    last received balise (K,) and step times (ns) of ``time_filter``.
    """
    odo, bal, ctl = res.odometer, res.balise, res.control
    K = len(odo["t"])
    est = {n: np.zeros((K, 2)) for n in filters}
    cov = {n: np.zeros((K, 2, 2)) for n in filters}
    truth = np.column_stack([res.truth["position"], res.truth["velocity"]])
    bal_idx = np.flatnonzero(bal["received"])
    bal_idx = bal_idx[np.argsort(bal["stamp"][bal_idx], kind="stable")]
    bi = 0
    last_bal = sc.start_position
    d_since = np.zeros(K)
    step_ns = []
    for k in range(K):
        tk = float(odo["stamp"][k])
        while bi < len(bal_idx) and bal["stamp"][bal_idx[bi]] <= tk:
            j = bal_idx[bi]
            r = BaliseReading(float(bal["stamp"][j]), int(bal["seq"][j]), int(bal["balise_id"][j]),
                              float(bal["position"][j]), float(bal["position_variance"][j]))
            for f in filters.values():
                f.update(r)
            last_bal = float(bal["position"][j])
            bi += 1
        if odo["received"][k]:
            r = OdometerReading(tk, int(odo["seq"][k]), float(odo["distance"][k]),
                                float(odo["speed"][k]), float(odo["speed_variance"][k]))
        else:
            r = OdometerReading(tk, int(odo["seq"][k]), received=False)
        for n, f in filters.items():
            if n == time_filter:
                t0 = time.perf_counter_ns()
                f.update(r)
                step_ns.append(time.perf_counter_ns() - t0)
            else:
                f.update(r)
            f.set_control(tk, float(ctl["target_acceleration"][k]))
            x, P = f.estimate()
            est[n][k], cov[n][k] = x, P
        d_since[k] = abs(truth[k, 0] - last_bal)
    rejected = {n: sum(c for r, c in f.counters.items() if r not in ("ok", "missing", "ignored"))
                for n, f in filters.items()}
    return est, cov, truth, d_since, np.array(step_ns), rejected


def q95(a, axis=0):
    return np.percentile(a, [2.5, 97.5], axis=axis)


def fmt(x, nd=4):
    if not np.isfinite(x):
        return "nan"
    if x == 0 or 1e-3 <= abs(x) < 1e5:
        return f"{x:.{nd}f}"
    return f"{x:.3e}"


# ------------------------------------------------------------------------------------------------
# 1 + 2 + 5: Wen Table III, the bound and the step time
# ------------------------------------------------------------------------------------------------

def wen_table(seeds, names, out_dir):
    sc = load_scenario("wen2017_subway")
    ab = sc.link.received_probability
    var = {n: [] for n in names}
    rejected = {n: 0 for n in names}
    err_all = {n: [] for n in names}
    sig_all = {n: [] for n in ROBUST if n in names}
    step_ns = []
    for s in track(range(seeds), "robust filter"):
        res = simulate(sc, seed=s)
        fl = make_filters(sc, names, ab)
        est, cov, truth, _, ns, rej = run(sc, res, fl, time_filter="robust")
        step_ns.append(ns)
        for n in names:
            e = est[n] - truth
            var[n].append(e.var(axis=0))
            rejected[n] += rej[n]
            err_all[n].append(e)
            if n in sig_all:
                sig_all[n].append(np.diagonal(cov[n], axis1=1, axis2=2))
    var = {n: np.array(v) for n, v in var.items()}
    print(f"\n## 1. Wen Table III on `wen2017_subway` ({seeds} seeds, alpha-bar = {ab:g}, "
          f"R = diag{{1, 0.01}}, q = {Q_WIND} N^2, T = 1 s)\n")
    print("Statistical variance of the estimation error over a run (per seed), mean over seeds "
          "[2.5 %, 97.5 % of seeds]; ratio = FOH / filter (mean of per-seed ratios).\n")
    print("| filter | var position (m^2) | var velocity ((m/s)^2) | FOH/filter pos | "
          "FOH/filter vel | rejected readings |")
    print("|---|---|---|---|---|---|")
    print("| paper: FOH | 8.4972 | 0.3226 | 1 | 1 | |")
    print("| paper: recursive filter | 5.1516 | 0.0518 | 1.649 | 6.228 | |")
    for n in names:
        v = var[n]
        lo, hi = q95(v)
        rat = var["foh"] / v if "foh" in var else np.full_like(v, np.nan)
        print(f"| {n} | {fmt(v[:, 0].mean())} [{fmt(lo[0])}, {fmt(hi[0])}] | "
              f"{fmt(v[:, 1].mean())} [{fmt(lo[1])}, {fmt(hi[1])}] | "
              f"{fmt(rat[:, 0].mean(), 2)} | {fmt(rat[:, 1].mean(), 2)} | {rejected[n]} |")

    # 2. the bound
    print(f"\n## 2. Theorem 2: Monte Carlo MSE (over {seeds} seeds) vs the bound Sigma(k|k)\n")
    print("Per step k: MSE_k = mean over seeds of e_k^2, bound_k = mean over seeds of "
          "Sigma_k (it depends on x^ through lambda_bar). 'holds' = fraction of steps with "
          "MSE <= bound; 'holds (stat)' allows the Monte Carlo error: MSE - bound <= "
          "z se with z for a 1e-3 family-wise false alarm (Bonferroni); tightness = MSE / bound "
          "(median, max over steps).\n")
    print("| filter | component | holds | holds (stat) | tightness median | tightness max |")
    print("|---|---|---|---|---|---|")
    from scipy.stats import norm
    for n in sig_all:
        e2 = np.array(err_all[n]) ** 2  # (seeds, K, 2)
        sg = np.array(sig_all[n])
        D = sg - e2
        mse, bnd = e2.mean(0), sg.mean(0)
        se = D.std(0, ddof=1) / math.sqrt(max(seeds, 2))
        z = norm.ppf(1 - 1e-3 / D[0].size)
        for c, cname in enumerate(("position", "velocity")):
            hold = np.mean(mse[:, c] <= bnd[:, c])
            hold_s = np.mean(D.mean(0)[:, c] >= -z * se[:, c])
            tight = mse[:, c] / bnd[:, c]
            print(f"| {n} | {cname} | {hold:.3f} | {hold_s:.3f} | {np.median(tight):.3g} | "
                  f"{tight.max():.3g} |")
    # plot the bound for the robust filters
    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
        fig, ax = plt.subplots(2, 1, figsize=(8, 6), sharex=True)
        t = np.arange(len(err_all[names[0]][0]))
        for n in sig_all:
            e2 = np.array(err_all[n]) ** 2
            for c in range(2):
                line, = ax[c].semilogy(t, e2.mean(0)[:, c], label=f"{n} MSE")
                ax[c].semilogy(t, np.array(sig_all[n]).mean(0)[:, c], "--",
                               color=line.get_color(), label=f"{n} bound")
        ax[0].set_ylabel("position m^2")
        ax[1].set_ylabel("velocity (m/s)^2")
        ax[1].set_xlabel("step k (T = 1 s)")
        ax[0].legend(fontsize=7, ncol=2)
        fig.suptitle("wen2017_subway: Monte Carlo MSE vs bound Sigma(k|k)")
        fig.tight_layout()
        fig.savefig(out_dir / "robust_bound.png", dpi=110)
        plt.close(fig)
    except ImportError:
        print("\n(matplotlib missing: no PNG)")

    ns = np.concatenate(step_ns) / 1e3
    print("\n## 5. Core step time of `robust` (one odometer period: predict (21) + update "
          "(22)/(24) + validation), this machine\n")
    print("| samples | median (us) | p99 (us) | max (us) |")
    print("|---|---|---|---|")
    print(f"| {ns.size} | {np.median(ns):.1f} | {np.percentile(ns, 99):.1f} | {ns.max():.1f} |")
    return var


# ------------------------------------------------------------------------------------------------
# 3: sweeps
# ------------------------------------------------------------------------------------------------

def sweeps(seeds, names, out_dir, quick):
    sc0 = load_scenario("wen2017_subway")
    fracs = [1.0, 0.7, 0.3] if quick else [1.0, 0.9, 0.8, 0.7, 0.6, 0.5, 0.4, 0.3]
    mism = [-0.5, 0.0, 0.5] if quick else [-0.5, -0.25, 0.0, 0.25, 0.5]
    tables = {}
    for label, values in (("received fraction", fracs), ("v^2 coefficient mismatch", mism)):
        rm = {n: [] for n in names}
        for val in values:
            if label == "received fraction":
                sc = sc0.with_changes(link=LinkParams(model="bernoulli", p=1.0 - val, r=1))
                ab = val
            else:
                d = sc0.train.davis
                sc = sc0.with_effects(Effects(resistance=ResistanceEffect(d.a, d.b,
                                                                          d.c * (1 + val))))
                ab = sc.link.received_probability
            se = {n: [] for n in names}
            for s in track(range(seeds), "sensitivity"):
                res = simulate(sc, seed=1000 + s)
                est, _, truth, _, _, _ = run(sc, res, make_filters(sc, names, ab))
                for n in names:
                    se[n].append((est[n] - truth) ** 2)
            for n in names:
                rm[n].append(np.sqrt(np.concatenate(se[n]).mean(0)))
        tables[label] = (values, {n: np.array(v) for n, v in rm.items()})
        print(f"\n## 3. Sweep: {label} (`wen2017_subway`, {seeds} seeds per point; RMSE over "
              "all steps and seeds; position m / velocity m/s)\n")
        print("| " + label + " | " + " | ".join(names) + " |")
        print("|---|" + "---|" * len(names))
        for i, val in enumerate(values):
            cells = [f"{rm[n][i][0]:.3f} / {rm[n][i][1]:.4f}" for n in names]
            v = f"{val:+.0%}" if label != "received fraction" else f"{val:.1f}"
            print(f"| {v} | " + " | ".join(cells) + " |")
    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
        for label, (values, rm) in tables.items():
            fig, ax = plt.subplots(1, 2, figsize=(10, 4))
            for n in names:
                ax[0].plot(values, rm[n][:, 0], "o-", label=n)
                ax[1].plot(values, rm[n][:, 1], "o-", label=n)
            ax[0].set_ylabel("position RMSE (m)")
            ax[1].set_ylabel("velocity RMSE (m/s)")
            for a in ax:
                a.set_xlabel(label)
                a.set_yscale("log")
                a.grid(True, which="both", alpha=0.3)
            ax[0].legend(fontsize=8)
            fig.suptitle(f"wen2017_subway: RMSE vs {label}")
            fig.tight_layout()
            slug = "received" if label == "received fraction" else "v2_mismatch"
            fig.savefig(out_dir / f"robust_sweep_{slug}.png", dpi=110)
            plt.close(fig)
    except ImportError:
        pass


# ------------------------------------------------------------------------------------------------
# 4: ETCS yardstick
# ------------------------------------------------------------------------------------------------

def etcs(seeds):
    sc = load_scenario("metro_demo")
    ab = sc.link.received_probability
    variants = [("foh", "foh", True), ("robust", "robust", True),
                ("robust_vel", "robust_vel", True), ("kf", "kf", True),
                ("oracle", "oracle", True),
                ("robust (speed + balises only)", "robust", False),
                ("robust_vel (speed + balises only)", "robust_vel", False),
                ("kf (speed + balises only)", "kf", False)]
    errs = {v[0]: [] for v in variants}
    rejected = {v[0]: 0 for v in variants}
    allow = []
    for s in track(range(seeds), "robust filter"):
        res = simulate(sc, seed=s)
        for use_d in (True, False):
            names = sorted({v[1] for v in variants if v[2] == use_d})
            est, _, truth, d_since, _, rej = run(sc, res, make_filters(sc, names, ab,
                                                                       use_distance=use_d))
            for lab, n, ud in variants:
                if ud == use_d:
                    errs[lab].append(np.abs(est[n][:, 0] - truth[:, 0]))
                    rejected[lab] += rej[n]
        allow.append(5.0 + 0.05 * d_since)
    allow = np.concatenate(allow)
    print(f"\n## 4. ETCS yardstick on `metro_demo` ({seeds} seeds, 10 Hz, "
          f"{len(allow)} samples): |position error| vs SUBSET-041's 5 m + 5 % of the "
          "distance since the last received balise\n")
    print(f"Allowance over the samples: median {np.median(allow):.1f} m, 5th percentile "
          f"{np.percentile(allow, 5):.1f} m.\n")
    print("| filter | p95 |error| (m) | max |error| (m) | p95 of error/allowance | "
          "fraction within allowance | rejected readings |")
    print("|---|---|---|---|---|---|")
    for lab, _, _ in variants:
        e = np.concatenate(errs[lab])
        r = e / allow
        print(f"| {lab} | {np.percentile(e, 95):.3f} | {e.max():.3f} | "
              f"{np.percentile(r, 95):.4f} | {np.mean(r <= 1.0):.5f} | {rejected[lab]} |")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", type=int, default=100, help="seeds for tables 1, 2, 5")
    ap.add_argument("--sweep-seeds", type=int, default=None,
                    help="seeds per sweep point (default: seeds // 5, at least 5)")
    ap.add_argument("--etcs-seeds", type=int, default=None,
                    help="seeds of metro_demo runs (default: seeds // 10, at least 3)")
    ap.add_argument("--quick", action="store_true", help="10 seeds, short sweeps")
    ap.add_argument("--markdown", action="store_true",
                    help="(tables are always printed as markdown; accepted for symmetry)")
    ap.add_argument("--skip", default="", help="comma list of sections to skip: wen,sweep,etcs")
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "out"))
    a = ap.parse_args(argv)
    seeds = 10 if a.quick and a.seeds == 100 else a.seeds
    sweep_seeds = a.sweep_seeds or max(seeds // 5, 5 if not a.quick else 3)
    etcs_seeds = a.etcs_seeds or max(seeds // 10, 3 if not a.quick else 1)
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    skip = set(filter(None, a.skip.split(",")))
    t0 = time.time()
    print("# Robust filter under packet dropouts (Wen et al. 2017): benchmark\n")
    print(f"seeds = {seeds}, sweep seeds = {sweep_seeds}, ETCS seeds = {etcs_seeds}; "
          "epsilon and gamma chosen per step (see robust_filter.py)")
    if "wen" not in skip:
        wen_table(seeds, ALL, out)
    if "sweep" not in skip:
        sweeps(sweep_seeds, ALL, out, a.quick)
    if "etcs" not in skip:
        etcs(etcs_seeds)
    print(f"\n(total wall time {time.time() - t0:.0f} s; PNGs in {out})")


if __name__ == "__main__":
    main()
