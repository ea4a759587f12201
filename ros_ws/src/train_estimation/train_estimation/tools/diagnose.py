"""`diagnose`: find what the simulation of a train gets wrong in measured data and name the cause.

    diagnose --bag BAG --line line.yaml --train train.yaml --out DIR

Reads the bag's ``odometer``, ``balise`` and ``control`` topics (a ``ground_truth`` topic, if
present, is never used), aligns the believed model (line.yaml, train.yaml) with the data, fits
one extended model per cause (docs/interfaces.md ``diagnose``: gradient, resistance, braking_rate,
odometer_scale, wheel_slip, bursty_link, brake_delay, mass, clock_drift, power_limit,
adhesion_section, traction_delay) and ranks them.

Output (DIR is created):
  DIR/report.json   cause, parameters, ranking, unexplained, untestable, evidence, gain
                    (docs/interfaces.md)
  DIR/model/        line.yaml, train.yaml, effects.yaml: the believed model extended by every
                    confirmed cause; run it with
                    python -m train_sim.generate --scenario S --model DIR/model --out BAG
  DIR/*.svg         residual acceleration of the believed and the extended model against
                    position (with the line profile and the fitted gradient section), against
                    speed and against the commands; the speed trace with slip episodes; f(t);
                    the loss-run histogram; the recorded commands replayed through both
                    models (replay.svg); the residual by phase against position and speed
                    with what is unexplained (residual_phases.svg)
  DIR/report.html   the report in one self-contained page (verdict first, plots embedded)
  DIR/inputs.json   the bag, line and train analysed and when (the page's header)

How to read the report:
  cause        the first confirmed cause; "none" when nothing is confirmed and nothing is
               left over, "unexplained" when nothing is confirmed and the residuals still
               hold structure that no listed cause explains
  ranking      every cause tested, best first, "none" among them, each with a status:
               confirmed (accepted by the score, its fit on half of the data predicts the
               other half better beyond that gain's own noise, its size is beyond what the
               data resolve, and it shows in every phase, speed, place and time it predicts,
               with the speed law it predicts: a gradient does not grow as v^2 as drag does),
               "not confirmed" (with why) or "rejected" (score not above none's). Only
               confirmed causes go into DIR/model. The score of a cause is
               the BIC-penalised log-likelihood ratio with the prior odds of "none" against
               the K causes tested, 2 (ll_cause - ll_null) - k ln n - 2 ln K (k: its
               parameter count, n: the number of measurements); > 0 means the data support
               the cause, "none" has score 0. With two effects the greedy refit ranks the
               second cause (scored on top of the first) second.
  unexplained  what the confirmed model leaves in the residuals (a calibrated test by phase,
               speed, position, time and command onsets): phase, where (m), when (s), speed
               (m/s), size (m/s^2) and the closest listed cause with why it does not fit;
               [] when nothing is left
  untestable   causes the data cannot test, with the reason (e.g. no braking, no balises)
  evidence     per cause: its score alone, log-likelihood gain, parameter count, n, the fit
               alone and the standard errors of its parameters
  gain         how much better the extended model predicts data not used for the fit, with
               the metric named (held-out speed RMSE for motion causes, balise position error
               for the odometer scale, stamp residual for the clock, log-likelihood per
               sample for the link)
Times in parameters are seconds since the first odometer stamp, on the train's stamp clock.

Exit status: 0 when a diagnosis was made (including "none"); 2 with one line on stderr saying
what is missing when the input is unusable (unreadable bag, no control, no odometer, no
balises, too short, never moving, missing or malformed YAML).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import shutil
import sys
import tempfile
import time
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
import yaml
from train_core.bagio import BagError, read_bag
from train_core.config import ConfigError, Section, load_yaml
from train_core.effects import Effects, effect_to_dict, parse_effects, true_line, true_train
from train_core.model import line_from_dict, load_line, load_train, train_from_dict

from train_estimation.core.offline.diagnose.result import jsonable
from train_estimation.core.offline.diagnose.verdict import SCORE_FORMULA  # noqa: F401 (help)
from train_estimation.core.offline.measured import TOPICS, MeasuredRun
from train_estimation.tools.common import (
    EXIT_INTERRUPTED,
    EXIT_OK,
    Progress,
    cannot_write,
    fail,
    one_line,
    pipe_safe,
    unclosed,
    unwritable,
)
from train_estimation.tools.diagnose_plots import PLOTS, write_plots
from train_estimation.tools.diagnose_unexplained import unexplained_line
from train_estimation.tools.report_html import write_report_html

# ------------------------------------------------------------------------------------------------
# Bag -> MeasuredRun
# ------------------------------------------------------------------------------------------------

def read_measured(path) -> MeasuredRun:
    """The measured run of a bag path; only the topics diagnose uses are decoded (a
    ground_truth topic is never read)."""
    return MeasuredRun.from_bag(read_bag(path, topics=TOPICS))


# ------------------------------------------------------------------------------------------------
# The extended model (DIR/model)
# ------------------------------------------------------------------------------------------------

def write_model(out: Path, dg, line_path: str, train_path: str, data) -> dict:
    """DIR/model: line.yaml (+ fitted gradient section), train.yaml (+ fitted Davis), and
    effects.yaml (the other confirmed causes, in a scenario's ``effects:`` syntax): each
    confirmed cause's ``train_core.effects`` dataclass (``model_effect`` of the cause), put
    where the cause says (``model_file``).

    ``mass`` goes into effects.yaml, not train.yaml: docs/interfaces.md's mass cause keeps the drive
    force computed for the believed mass, which is what train.yaml's mass is in the simulator;
    the effect makes the world's train heavier or lighter exactly as in the data.

    A fitted value the files cannot hold (e.g. a gradient beyond line.yaml's +-60 per mille) is
    left out of the model with a note (printed in the summary and written into the files'
    header), never clipped silently: the report keeps the fit as it is."""
    from train_estimation.core.offline.diagnose import BY_NAME

    d = out / "model"
    d.mkdir(parents=True, exist_ok=True)
    m = _Model(load_yaml(line_path), load_yaml(train_path), line_path)
    ctx = model_context(dg, data, m.line.length)
    for a in dg.accepted:
        cause = BY_NAME[a.cause]
        eff, note = cause.model_effect(a, ctx)
        if eff is None:
            if note:
                m.skipped.append(note)
            continue
        m.add(a.cause, cause.model_file, cause.effect_field, eff, note, max(ctx.duration, 1.0))
    head = ("# written by diagnose: the believed {what} extended by the confirmed causes\n"
            "# ({causes}); times are seconds from the start of the run\n"
            + "".join(f"# {s}\n" for s in m.skipped))
    causes = ", ".join(a.cause for a in dg.accepted) or "none"
    (d / "line.yaml").write_text(head.format(what="line", causes=causes)
                                 + yaml.safe_dump(jsonable(m.line_d), sort_keys=False))
    (d / "train.yaml").write_text(head.format(what="train", causes=causes)
                                  + yaml.safe_dump(jsonable(m.train_d), sort_keys=False))
    (d / "effects.yaml").write_text(
        head.format(what="model's effects (train_sim scenario `effects:` syntax)",
                    causes=causes)
        + (yaml.safe_dump(jsonable(m.effects), sort_keys=False) if m.effects else "{}\n"))
    # what we wrote must load (the simulator reads these files)
    line_from_dict(load_yaml(d / "line.yaml"), str(d / "line.yaml"))
    train_from_dict(load_yaml(d / "train.yaml"), str(d / "train.yaml"))
    parse_effects(Section(load_yaml(d / "effects.yaml"), str(d / "effects.yaml")),
                  max(ctx.duration, 1.0))
    return {"dir": d, "effects": m.effects, "notes": m.notes + m.effect_notes + m.skipped}


def model_context(dg, data, line_length: float):
    """The diagnosis' times on true time: the run's length and the accepted clock drift."""
    from train_estimation.core.offline.diagnose import BY_NAME, ModelContext

    n = len(data.odo_stamp)
    drift = sum(BY_NAME[a.cause].clock_drift(a) for a in dg.accepted)
    duration = float(np.ptp(data.odo_stamp)) if n else 0.0
    return ModelContext(duration=duration / (1.0 + drift), line_length=line_length,
                        drift=drift, t_first=float(np.min(data.odo_stamp)) if n else 0.0,
                        evidence=dg.evidence or {}, odo_stamp=data.odo_stamp,
                        odo_speed=data.odo_speed)


class _Model:
    """The model directory's contents while effects are added to them."""

    def __init__(self, line_d: dict, train_d: dict, line_path: str):
        self.line_d, self.train_d = line_d, train_d
        self.line = line_from_dict(line_d, line_path)
        self.train = train_from_dict(train_d, "train.yaml")
        self.effects: dict = {}
        self.notes, self.effect_notes, self.skipped = [], [], []

    def add(self, name: str, where: str, field: str, eff, note, duration: float) -> None:
        """Put one effect into line.yaml, train.yaml or effects.yaml; a value the file cannot
        hold (the loaders and the simulator's parser decide) is skipped with a note."""
        effects = Effects(**{field: eff})
        try:
            if where == "line":
                new_line = true_line(self.line, effects)
                grads = [{"start": float(s.start), "end": float(s.end),
                          "permille": round(float(s.permille), 4)} for s in new_line.gradients]
                line_from_dict({**self.line_d, "gradients": grads}, "line.yaml")
                self.line, self.line_d["gradients"] = new_line, grads
            elif where == "train":
                new = true_train(self.train, effects)
                for f in dataclasses.fields(new):
                    v = getattr(new, f.name)
                    if v != getattr(self.train, f.name):
                        self.train_d[f.name] = dataclasses.asdict(v) \
                            if dataclasses.is_dataclass(v) else v
                self.train = new
            else:
                params = effect_to_dict(eff)
                parse_effects(Section({field: params}, "effects.yaml"), duration)
                self.effects[field] = params
        except ConfigError as exc:
            self.skipped.append(f"{name} not in the model ({one_line(exc)})")
            return
        if note:
            (self.notes if where != "effects" else self.effect_notes).append(note)


# ------------------------------------------------------------------------------------------------
# Summary and CLI
# ------------------------------------------------------------------------------------------------

def _fmt_params(p: dict) -> str:
    parts = []
    for k, v in p.items():
        if isinstance(v, float):
            parts.append(f"{k}={v:.4g}")
        elif isinstance(v, list):
            parts.append(f"{k}=" + ",".join(
                "[" + ",".join(f"{x:.1f}" if isinstance(x, float) else str(x) for x in iv) + "]"
                if isinstance(iv, list) else str(iv) for iv in v[:4]) + ("..." if len(v) > 4
                                                                         else ""))
        else:
            parts.append(f"{k}={v}")
    return " ".join(parts)


def summary(dg, bag_path, data, elapsed: float, model: dict) -> list[str]:
    n_odo, n_bal = len(data.odo_stamp), len(data.balise_stamp)
    dur = float(np.ptp(data.odo_stamp)) if n_odo else 0.0
    out = [f"diagnose {bag_path}: {dur:.0f} s, {n_odo} odometer samples, {n_bal} balise "
           f"readings, {elapsed:.1f} s"]
    # what was done to the data before the analysis (readings left out, values taken from
    # the map or train.yaml): on the terminal too, not only in report.json
    out += [f"data: {n}" for n in ((dg.evidence or {}).get("_model") or {}).get("notes") or []]
    out.append(f"{'rank':<5}{'cause':<16}{'score':>10}  {'status':<14} parameters")
    checks = (((dg.evidence or {}).get("_model") or {}).get("confirmation") or {}).get(
        "checks") or {}
    for i, r in enumerate(dg.ranking[:6]):
        out.append(f"{i + 1:<5}{r.cause:<16}{r.score:>10.1f}  {r.status or '-':<14} "
                   f"{_fmt_params(r.parameters)}")
        if r.why:
            out.append(f"{'':<33}why: {r.why}")
        caveat = (checks.get(r.cause) or {}).get("caveat")
        if r.status == "confirmed" and caveat:
            # what one run's data cannot tell the confirmed cause from (docs/diagnose.md)
            out.append(f"{'':<33}caveat: {caveat}")
    if len(dg.ranking) > 6:
        out.append(f"     ... {len(dg.ranking) - 6} more in report.json")
    for u in dg.unexplained:
        out.append(unexplained_line(u))
    for u in dg.untestable:
        out.append(f"untestable: {u['cause']} ({u['why']})")
    g = dg.gain or {}
    if g.get("before") is not None and g.get("after") is not None:
        out.append(f"gain: {g.get('metric')}: {g['before']:.4g} -> {g['after']:.4g}")
    notes = list(model.get("notes", []))
    if model.get("effects"):
        notes.append("effects.yaml: " + ", ".join(model["effects"]))
    if notes:
        out.append("model: " + "; ".join(notes))
    out.append(f"cause: {dg.cause}")
    return out


def inputs_record(args, line, train, data) -> dict:
    """DIR/inputs.json: what was analysed and when, for the report's header."""
    n_odo = len(data.odo_stamp)
    dur = float(np.ptp(data.odo_stamp)) if n_odo else 0.0
    return {"bag": str(Path(args.bag).resolve()), "line": str(Path(args.line).resolve()),
            "line_name": line.name, "train": str(Path(args.train).resolve()),
            "train_name": train.name,
            "data": f"{dur:.0f} s, {n_odo} odometer samples, {len(data.balise_stamp)} balise "
                    f"readings, {len(data.ctrl_stamp)}"
                    " commands",
            "date": datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC")}


@pipe_safe
def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="diagnose", description=__doc__.splitlines()[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter,
                                epilog="\n".join(__doc__.splitlines()[2:]))
    p.add_argument("--bag", required=True,
                   help="measured data: rosbag2 (MCAP) with odometer, balise and control")
    p.add_argument("--line", required=True, help="line.yaml as the railway believes it")
    p.add_argument("--train", required=True, help="train.yaml as the railway believes it")
    p.add_argument("--out", required=True,
                   help="output directory: report.json, plots and model/ (created)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument("--no-plots", action="store_true",
                   help="no SVG plots (report.json, model/ and report.html without "
                        "figures)")
    args = p.parse_args(argv)
    from train_estimation.core.offline.diagnose import DiagnoseError, diagnose

    t0 = time.perf_counter()
    bag = None
    out = Path(args.out)
    why = unwritable(out)  # checked first: an analysis is not run to be lost
    if why:
        return fail("diagnose", f"--out {args.out}: {why}; name a directory you can write")
    stage, made = None, not out.exists()
    try:
        try:
            line, train = load_line(args.line), load_train(args.train)
            bag = read_bag(args.bag, topics=TOPICS)
            data = MeasuredRun.from_bag(bag)
            if unclosed(bag) and not args.quiet:
                print(f"diagnose: note: {args.bag}{unclosed(bag)}", file=sys.stderr)
            bar = None if args.quiet else Progress("diagnose", what_width=36)
            dg = diagnose(data, line, train, progress=bar)
        except (ConfigError, BagError) as exc:
            return fail("diagnose", str(exc))
        except DiagnoseError as exc:  # a truncated bag is the usual reason: named, repaired
            return fail("diagnose", f"cannot diagnose {args.bag}: {exc}{unclosed(bag)}")
        elapsed = time.perf_counter() - t0
        out.mkdir(parents=True, exist_ok=True)
        stage = Path(tempfile.mkdtemp(prefix=f".{out.name}.", dir=out))
        # every output is written into a stage inside DIR, then moved into DIR at once, over
        # what an earlier run wrote there: an interrupted run leaves DIR as it was, and a run
        # without plots does not show an earlier run's plots in its report.html
        (stage / "report.json").write_text(json.dumps(dg.to_json(), indent=1) + "\n")
        (stage / "inputs.json").write_text(json.dumps(inputs_record(args, line, train, data))
                                           + "\n")
        model = write_model(stage, dg, args.line, args.train, data)
        if not args.no_plots:
            write_plots(dg.series, stage, dg)
        lines = summary(dg, args.bag, data, elapsed, model)
        write_report_html(stage, "diagnose")
        _publish(stage, out)
        lines.insert(-1, f"report: {out / 'report.html'}")  # "cause: ..." stays last
        print("\n".join(lines))
        return EXIT_OK
    except KeyboardInterrupt:
        print("diagnose: interrupted; nothing written", file=sys.stderr)
        return EXIT_INTERRUPTED
    except BrokenPipeError:
        raise  # the reader of stdout went away: pipe_safe
    except OSError as exc:
        return cannot_write("diagnose", args.out, exc)
    finally:
        if stage is not None:
            shutil.rmtree(stage, ignore_errors=True)
        if made and out.is_dir() and not any(out.iterdir()):
            out.rmdir()  # a run that wrote nothing leaves no DIR behind


# what diagnose writes into DIR: an earlier run's are replaced by this run's, or removed (the
# plots' PNG names too, which earlier versions wrote)
OUTPUTS = ("report.json", "inputs.json", "report.html", "model",
           *(name for name, _ in PLOTS), *(name[:-4] + ".png" for name, _ in PLOTS))


def _publish(stage: Path, out: Path) -> None:
    """Move the staged outputs into ``out``, removing an earlier run's outputs first (only
    the names diagnose writes: a user's own files in DIR are left)."""
    for name in OUTPUTS:
        old = out / name
        if old.is_dir() and not old.is_symlink():
            shutil.rmtree(old)
        elif old.exists() or old.is_symlink():
            old.unlink()
    for item in stage.iterdir():
        os.replace(item, out / item.name)


if __name__ == "__main__":
    sys.exit(main())
