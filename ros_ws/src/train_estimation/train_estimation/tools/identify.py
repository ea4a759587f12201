"""`identify`: fit a train's parameters from a bag and write a fitted train.yaml.

    identify --bag BAG --line line.yaml --train train.yaml --out fitted_train.yaml

Reads ``odometer``, ``balise`` and ``control`` from the bag (docs/interfaces.md; ground truth,
if present, is not used), fits the Davis coefficients, mass, rotary allowance and braking rate
as far as the data identify them (train.identify), and writes ``train.yaml`` with the fitted
values, their standard errors as comments and an ``identification`` block of extra keys, plus a
plot of the fit beside it (``<out>.png``). Parameters the data cannot identify keep the prior
value and are marked so. A bag that lacks what the fit needs gets a one-line reason naming what
is missing and which parameters cannot be identified, exit code 2, and no output file.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import yaml
from train_core.bagio import BagError, read_bag
from train_core.config import ConfigError
from train_core.model import TrainParams, load_line, load_train

from train_estimation.core.offline.measured import MeasuredRun
from train_estimation.tools.common import (
    EXIT_OK,
    Progress,
    cannot_write,
    fail,
    pipe_safe,
    unclosed,
    unwritable,
)


def train_to_yaml(train: TrainParams, res, prior: TrainParams, source: str) -> str:
    """The fitted train.yaml text: docs/interfaces.md keys, SEs as comments, extras as a block."""
    se, ok = res.std_errors, res.identifiable

    d, d0 = train.davis, prior.davis

    def note(name):
        s = se.get(name, math.nan)
        if not ok.get(name, False):
            if "not separable" in str(res.reasons.get(name, "")) and math.isfinite(s):
                return (f"fitted, standard error {s:.4g}, but not separable from the other "
                        "parameters (see identification.reasons)")
            if name.startswith("davis."):
                # the fit holds a Davis term at the prior *per unit of effective mass* (the
                # specific resistance is what the data constrain); with a fitted mass the
                # value in N then differs from train.yaml's, so say which prior was kept
                v, v0 = getattr(d, name[6:]), getattr(d0, name[6:])
                if not math.isclose(v, v0, rel_tol=1e-9, abs_tol=1e-12):
                    return (f"not identifiable from this run: the prior per unit of effective "
                            f"mass kept, scaled by the fitted mass (prior {v0:.6g})")
            return "not identifiable from this run: prior kept"
        return f"fitted, standard error {s:.4g}" if math.isfinite(s) else "fitted"

    lines = [
        f"# train.yaml fitted by `identify` from {source}",
        f"# prior: {prior.name}; values the data cannot identify keep the prior's value.",
        f"name: {train.name}",
        f"mass: {train.mass:.6g}                 # kg, {note('mass')}",
        f"rotary_allowance: {train.rotary_allowance:.6g}    # -, {note('rotary_allowance')}",
        "davis:                       # resistance a + b v + c v^2, in N",
        f"  a: {d.a:.6g}                  # N, {note('davis.a')}",
        f"  b: {d.b:.6g}                  # N/(m/s), {note('davis.b')}",
        f"  c: {d.c:.6g}                  # N/(m/s)^2, {note('davis.c')}",
        "brake:",
        f"  time_constant: {train.brake.time_constant:g}   # s, from the prior",
        f"  delay: {train.brake.delay:.4g}           # s, "
        + (f"the prior's {prior.brake.delay:g} + the commands' time offset "
           f"{res.diagnostics['command_offset_s']:+.3f} +- "
           f"{res.diagnostics.get('command_offset_se', math.nan):.3f}"
           if train.brake.delay != prior.brake.delay else "from the prior"),
        f"  braking_rate: {train.brake.braking_rate:.4g}    # -, {note('braking_rate')}",
        f"odometer: {{speed_std: {train.odometer_speed_std:g}, "
        f"distance_std: {train.odometer_distance_std:g}}}   # m/s, m (prior)",
        f"balise: {{position_std: {train.balise_position_std:g}}}   # m (prior)",
        "performance:                 # ATO limits (prior)",
        f"  max_traction: {train.performance.max_traction:g}",
        f"  service_brake: {train.performance.service_brake:g}",
        f"  emergency_brake: {train.performance.emergency_brake:g}",
        f"  max_jerk: {train.performance.max_jerk:g}",
    ]
    extra = {"identification": {
        "standard_errors": {k: float(v) for k, v in se.items()
                            if k in ok and isinstance(v, float | int) and math.isfinite(v)},
        "identifiable": {k: bool(v) for k, v in ok.items()},
        "reasons": {k: str(v) for k, v in res.reasons.items()},
        "rule": res.rule,
        "correlations": correlations(res),
        "variance_inflation": {k: round(float(v), 3) for k, v in res.variance_inflation.items()},
        "fixed_by_rule": [{"name": f["name"], "rule": f["rule"],
                           "relative_se": round(f["relative_se"], 4),
                           "variance_inflation": round(f["variance_inflation"], 3),
                           "correlations": {k: round(r, 4) for k, r in f["correlations"].items()}}
                          for f in res.fixed_by_rule],
        "force_at_reference_speed": {k: float(v) for k, v in
                                     res.force_at_reference_speed.items()},
        "mass_if_davis_nominal_kg": [float(x) for x in res.mass_if_davis_nominal],
    }}
    return "\n".join(lines) + "\n# extra keys (docs/interfaces.md allows them): what the fit " \
        "knows\n" \
        + yaml.safe_dump(extra, sort_keys=False, width=100)


# what the fitted (specific) parameters are, for the correlation table
FITTED_LEGEND = ("alpha, beta, gamma = davis a, b, c / M_eff; k = traction_gain = M_prior / mass;"
                 " kf = scaled_braking_rate = k braking_rate; kappa = 1 / (1 + rotary_allowance)")
SHORT = {"traction_gain": "k", "scaled_braking_rate": "kf"}


def correlations(res) -> dict:
    """Correlations of the final free (fitted) parameters as {name: {other: r}}."""
    names = list(res.free_names)
    if res.correlation is None:
        return {}
    return {a: {b: round(float(res.correlation[i, j]), 4) for j, b in enumerate(names) if j != i}
            for i, a in enumerate(names)}


def print_identifiability(res, out=None) -> None:
    """The force at the reference speed, the correlations and inflation factors of the free
    parameters, the parameters the rule fixed, and the rule (to ``out``, default stdout)."""
    out = sys.stdout if out is None else out
    off = res.diagnostics.get("command_offset_s")
    if off is not None:
        se = res.diagnostics.get("command_offset_se", math.nan)
        print(f"commands act {off:+.3f} s +- {se:.3f} s after their stamps (profiled; every "
              "standard error above holds this doubt)", file=out)
        if "command_offset" in res.reasons:
            print(f"  {res.reasons['command_offset']}", file=out)
    pv = res.diagnostics.get("position_offset_var", math.nan)
    if math.isfinite(pv):
        print(f"the run placed on the line at odometer distance 0 = "
              f"{res.diagnostics['position_offset_m']:.2f} m +- {math.sqrt(pv):.2f} m (the "
              f"balises' median offset; every standard error above holds this doubt)", file=out)
    if "position_offset" in res.reasons:
        print(f"  {res.reasons['position_offset']}", file=out)
    f = res.force_at_reference_speed
    if f:
        print(f"resistance force at {f['speed']:.1f} m/s (median moving speed): fitted "
              f"{f['fitted']:.6g} N +- {f['std_error']:.3g} N, prior {f['prior']:.6g} N "
              f"({f['z_vs_prior']:+.1f} SE from the prior)", file=out)
    names = list(res.free_names)
    if res.correlation is not None and names:
        print(f"correlations of the fitted parameters ({FITTED_LEGEND}):", file=out)
        print(" " * 8 + "".join(f"{SHORT.get(n, n):>8}" for n in names) + f"{'VIF':>10}",
              file=out)
        for i, a in enumerate(names):
            row = "".join(f"{res.correlation[i, j]:>8.3f}" for j in range(len(names)))
            print(f"{SHORT.get(a, a):<8}{row}  {res.variance_inflation.get(a, math.nan):>8.3g}",
                  file=out)
    for fx in res.fixed_by_rule:
        print(f"held at the prior: {fx['name']}: {res.reasons.get(fx['name'], fx['rule'])}",
              file=out)
    for name in names:
        if not res.identifiable.get(name, True):
            print(f"not identifiable: {name}: {res.reasons.get(name, '')}", file=out)
    if res.rule:
        print(f"rule: {res.rule}", file=out)


def plot_fit(res, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    s = res.series
    fig, axes = plt.subplots(2, 1, figsize=(10, 6), sharex=True)
    axes[0].plot(s["t"], s["speed_measured"], ".", ms=2, label="odometer speed")
    axes[0].plot(s["t"], s["speed_smoothed"], lw=1, label="model fit (smoothed)")
    axes[0].set_ylabel("speed (m/s)")
    axes[0].legend(fontsize=8)
    axes[1].plot(s["t"], s["speed_measured"] - s["speed_smoothed"], lw=0.6)
    axes[1].set_ylabel("residual (m/s)")
    axes[1].set_xlabel("time (s)")
    for ax in axes:
        ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


@pipe_safe
def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="identify", description=__doc__.splitlines()[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter,
                                epilog="\n".join(__doc__.splitlines()[2:]))
    p.add_argument("--bag", required=True, help="rosbag2 (MCAP) with odometer, balise, control")
    p.add_argument("--line", required=True, help="line.yaml of the line the train ran on")
    p.add_argument("--train", required=True, help="train.yaml: the prior")
    p.add_argument("--out", required=True, help="fitted train.yaml to write")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument("--commands-as-stamped", action="store_true",
                   help="take the commands to act when stamped (a producer known to stamp "
                        "them so) instead of profiling their time offset (docs/identify.md)")
    args = p.parse_args(argv)
    from train_estimation.core.offline.identify import IdentificationError, SIConfig, identify

    bag = None
    out = Path(args.out)
    plot = out.with_suffix(".png")
    # where the outputs go is checked first: a fit is not run to be lost or to overwrite
    # itself (--out fit.png named the plot and the fitted train.yaml the same file)
    if out.suffix.lower() == ".png" or out.is_dir():
        eg = out / "fit.yaml" if out.is_dir() else out.with_suffix(".yaml")
        return fail("identify", f"--out {args.out}: name the fitted train.yaml, e.g. {eg} "
                                f"(its plot goes beside it as .png)")
    why = unwritable(out.parent)
    if why:
        return fail("identify", f"--out {args.out}: {why}; name a file in a folder you can "
                                f"write")
    try:
        line, prior = load_line(args.line), load_train(args.train)
        bag = read_bag(args.bag)
        if unclosed(bag) and not args.quiet:
            print(f"identify: note: {args.bag}{unclosed(bag)}", file=sys.stderr)
        data = MeasuredRun.from_bag(bag).to_identify()
        cfg = SIConfig(command_offsets=None) if args.commands_as_stamped else SIConfig()
        res = identify(data, line, prior, cfg,
                       progress=None if args.quiet else Progress("identify"))
    except (ConfigError, BagError) as exc:
        return fail("identify", str(exc))
    except IdentificationError as exc:  # a truncated bag is the usual reason: named, with the
        return fail("identify", f"cannot fit {args.bag}: {exc}{unclosed(bag)}")  # repair
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(train_to_yaml(res.train, res, prior, args.bag))
        plot_fit(res, plot)
    except OSError as exc:
        return cannot_write("identify", args.out, exc)
    load_train(out)  # what we wrote must be a valid train.yaml
    print(f"{'parameter':<18}{'prior':>14}{'fitted':>14}{'std err':>12}  identifiable")
    for name, get in (("davis.a", lambda t: t.davis.a), ("davis.b", lambda t: t.davis.b),
                      ("davis.c", lambda t: t.davis.c), ("mass", lambda t: t.mass),
                      ("rotary_allowance", lambda t: t.rotary_allowance),
                      ("braking_rate", lambda t: t.brake.braking_rate)):
        se = res.std_errors.get(name, math.nan)
        print(f"{name:<18}{get(prior):>14.6g}{get(res.train):>14.6g}{se:>12.4g}  "
              f"{'yes' if res.identifiable.get(name) else 'no'}")
    print_identifiability(res)
    print(f"wrote {out} and {plot}")
    return EXIT_OK


if __name__ == "__main__":
    sys.exit(main())
