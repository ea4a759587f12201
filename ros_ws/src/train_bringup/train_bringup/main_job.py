"""The main job (`./run demo`): metro_demo end to end, then a short report.

Starts the simulator, the estimators, the zone controller and the recorder as separate processes
(each resolved as `ros2 run` would), waits for the simulator to finish its run, stops every
process it started by PID, checks the recorded bag offline and prints a report.

The estimators: `robust_filter` (Wen et al. 2017) on `estimate/robust`, and two instances of
`gsma_estimator`: node `gsma_estimator` runs Zheng et al.'s GSMA (`algorithm: gsma`, source
"gsma") on `estimate/gsma`, node `kf_estimator` the exact Kalman filter of the same braking
model beside it (`algorithm: kf`, source "kf"), remapped to `estimate/kf` and `odom/kf`. The
zone controller follows `estimate/robust`. The bag holds every topic, the Odometry outputs and
`/diagnostics`.

Pure orchestration (subprocess): no rclpy in this process. Exit code 0 when every process ran and
stopped cleanly and the checks passed, 1 otherwise.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import time
from pathlib import Path

from train_core.procs import resolve_executable as executable
from train_core.procs import stop_process

NS = "/train"
# node name -> (executable, its estimate topic, extra arguments)
ESTIMATORS = {
    "robust_filter": ("robust_filter", "estimate/robust", []),
    "gsma_estimator": ("gsma_estimator", "estimate/gsma", ["-p", "algorithm:=gsma"]),
    "kf_estimator": ("gsma_estimator", "estimate/kf",
                     ["-p", "algorithm:=kf", "-r", "__node:=kf_estimator",
                      "-r", "estimate/gsma:=estimate/kf", "-r", "odom/gsma:=odom/kf"]),
}
# what each estimator's `source` in the report stands for
LEGEND = {
    "robust_filter": "robust_filter = Wen et al. 2017's robust filter (estimate/robust)",
    "gsma_estimator": "gsma = Zheng et al. 2015's GSMA (estimate/gsma)",
    "kf_estimator": "kf = the exact Kalman filter of the same braking model, the reference "
                    "beside it (estimate/kf)",
}


class SimProgress:
    """A progress bar (stderr) of the simulated time, read from the simulator's log lines
    "simulated T of D s" (every 5 % of the run) as they appear; ``waiting`` keeps the last line
    in which the world said what it stands waiting for (a reader not matched, an estimate that
    does not come), which a run that does not finish reports."""

    LINE = re.compile(rb"simulated ([0-9.]+) of ([0-9.]+) s")
    WAIT = re.compile(rb"\]: ((?:waiting for subscribers|paced at t =)[^\n]*)")

    def __init__(self, log: Path, duration: float):
        from train_core.progress import bar

        self.log, self.offset, self.done = log, 0, 0.0
        self.waiting = ""
        self.bar = bar(round(duration), "simulating (s)")

    def update(self) -> None:
        try:
            with open(self.log, "rb") as fh:
                fh.seek(self.offset)
                chunk = fh.read()
        except OSError:
            return
        end = chunk.rfind(b"\n") + 1  # whole lines only; the rest is read next time
        self.offset += end
        found = self.LINE.findall(chunk[:end])
        waits = self.WAIT.findall(chunk[:end])
        if waits:
            self.waiting = waits[-1].decode(errors="replace")
        if found:
            t = round(float(found[-1][0]))
            self.bar.update(max(0, min(t, self.bar.total) - self.bar.n))

    def close(self) -> None:
        self.update()
        self.bar.close()


class Processes:
    """Processes this job started, stopped by PID only."""

    def __init__(self, logdir: Path):
        self.logdir = logdir
        self.procs: dict[str, subprocess.Popen] = {}

    def start(self, name: str, cmd: list[str]) -> subprocess.Popen:
        log = open(self.logdir / f"{name}.log", "wb")
        proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT)
        log.close()
        self.procs[name] = proc
        return proc

    def stop(self, name: str, timeout: float = 15.0) -> int | None:
        return stop_process(self.procs[name], timeout)

    def stop_all(self) -> dict[str, int | None]:
        return {name: self.stop(name) for name in reversed(list(self.procs))}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="main_job", description=__doc__.splitlines()[0])
    p.add_argument("--scenario", default="metro_demo", help="scenario name (default metro_demo)")
    p.add_argument("--rate-factor", type=float, default=20.0,
                   help="simulated seconds per wall second (default 20)")
    p.add_argument("--duration", type=float, default=-1.0,
                   help="s of simulated time (default: the scenario's)")
    p.add_argument("--out", default=None, help="output folder (default out/demo-<time>)")
    p.add_argument("--estimators", default=",".join(ESTIMATORS),
                   help="comma-separated estimator nodes to run (default all: "
                        f"{', '.join(ESTIMATORS)})")
    args = p.parse_args(argv)

    repo = Path(os.environ.get("TRAIN_REPO", Path.cwd()))
    out = Path(args.out) if args.out else repo / "out" / time.strftime("demo-%Y%m%d-%H%M%S")
    out.mkdir(parents=True, exist_ok=True)
    logs = out / "logs"
    logs.mkdir(exist_ok=True)
    bag = out / "bag"
    summary_file = out / "simulator_summary.json"
    ros = ["--ros-args", "-r", f"__ns:={NS}", "-p", "use_sim_time:=true"]

    from train_core.config import ConfigError

    from train_sim.scenario import load_scenario

    try:
        sc = load_scenario(args.scenario)
    except ConfigError as exc:
        print(f"main_job: {exc}", file=sys.stderr)
        return 2
    line_file, train_file = sc.line_path, sc.train_path

    # Estimates of time t are output at sim time t + delay; at rate factor r that is delay / r
    # of wall time for the readings of t to cross DDS and the executor: keep it ~50 ms of wall.
    delay = max(0.05, 0.05 * args.rate_factor)
    est = ["-p", "control_clock:=same",  # the simulator stamps everything on one clock
           "-p", f"output_delay:={delay}", "-p", f"initial_position:={sc.start_position}",
           "-p", f"odometer_rate:={sc.odometer_rate}", "-p", f"line_file:={line_file}",
           "-p", f"train_file:={train_file}"]
    wanted = {"recorder", *filter(None, args.estimators.split(","))}
    unknown = sorted(wanted - {"recorder", *ESTIMATORS})
    if unknown:
        print(f"main_job: --estimators: unknown {unknown} (known: {', '.join(ESTIMATORS)})",
              file=sys.stderr)
        return 2
    recorded = ["odometer", "balise", "control", "ground_truth", "movement_authority",
                *(ESTIMATORS[n][1] for n in ESTIMATORS if n in wanted),
                *("odom/" + ESTIMATORS[n][1].split("/")[1] for n in ESTIMATORS if n in wanted),
                "/diagnostics"]
    plan: list[tuple[str, str, str, list[str]]] = [
        ("train_estimation", "recorder", "recorder",
         ["-p", f"bag:={bag}", "-p", f"topics:=[{', '.join(recorded)}]"]),
        *(("train_estimation", exe, name, [*est, *extra])
          for name, (exe, _, extra) in ESTIMATORS.items()),
    ]
    consumers = [(pkg, exe, name, extra) for pkg, exe, name, extra in plan
                 if name in wanted and executable(pkg, exe) is not None]
    bag_recorded = any(name == "recorder" for _, _, name, _ in consumers)
    state_topic = ("estimate/robust" if any(n == "robust_filter" for _, _, n, _ in consumers)
                   else "ground_truth")
    # An estimator outputs only once its readers are matched (the recorder, the pacing
    # simulator, the zone controller for the state topic): none misses the first estimates.
    consumers = [(pkg, exe, name, extra if name == "recorder" else
                  [*extra, "-p", "wait_for_subscribers:="
                   f"{int(bag_recorded) + 1 + int(name == 'robust_filter')}"])
                 for pkg, exe, name, extra in consumers]
    zc_extra = ["-p", f"state_topic:={state_topic}", "-p", f"line_file:={line_file}"]
    # Reproducible runs (same scenario and seed, same bag whatever the machine's load):
    # - the train starts braked with no authority (the zone controller's expected start-up
    #   state), set at t = 0 rather than whenever the controller's first message arrives;
    # - the world is paced by the estimates and authorities it receives (at most `lead` ahead
    #   of their stamps: enough for an estimate's output delay and the controller's 1 s period,
    #   less than its 3 s staleness limit): a process stalled for some wall time holds the world
    #   back instead of being judged stale in simulated time (a brake that depends on the load);
    # - /clock runs on past the end until the estimators have released their last estimates.
    pace = [ESTIMATORS[name][1] for _, _, name, _ in consumers if name in ESTIMATORS]
    pace.append("movement_authority")
    lead = delay + 1.2
    sim_extra = ["-p", f"scenario:={args.scenario}", "-p", f"rate_factor:={args.rate_factor}",
                 "-p", f"duration:={args.duration}", "-p", f"summary_file:={summary_file}",
                 "-p", f"wait_for_subscribers:={len(consumers)}",
                 "-p", f"wait_for_truth_subscribers:={int(bag_recorded)}",
                 "-p", "start_with_emergency_brake:=true", "-p", f"end_linger:={2 * delay}",
                 "-p", f"max_lead:={lead}", "-p", f"pace_topics:=[{','.join(pace)}]"]

    procs = Processes(logs)
    t0 = time.monotonic()
    failed: list[str] = []
    try:
        for pkg, exe, name, extra in consumers:
            procs.start(name, [str(executable(pkg, exe)), *ros, *extra])
        procs.start("zone_controller",
                    [str(executable("train_sim", "zone_controller")), *ros, *zc_extra])
        # The simulator is the clock: it must not run on sim time itself.
        sim = procs.start("simulator", [str(executable("train_sim", "simulator")), "--ros-args",
                                        "-r", f"__ns:={NS}", *sim_extra])
        print(f"main job: {args.scenario} at {args.rate_factor:g}x real time; "
              f"processes {list(procs.procs)}; logs in {logs}", flush=True)
        limit = (sc.duration if args.duration < 0 else args.duration) / args.rate_factor + 120
        watch = SimProgress(logs / "simulator.log",
                            sc.duration if args.duration < 0 else args.duration)
        while sim.poll() is None:
            watch.update()
            if time.monotonic() - t0 > limit:  # (watch read the log just above)
                failed.append("simulator (did not finish in time"
                              + (f"; it last said: {watch.waiting})" if watch.waiting else ")"))
                break
            for name, proc in procs.procs.items():
                if name != "simulator" and proc.poll() is not None:
                    failed.append(f"{name} (exited early with {proc.returncode})")
            if failed:
                break
            time.sleep(0.2)
    except KeyboardInterrupt:
        failed.append("interrupted")
    finally:
        if "watch" in locals():
            watch.close()
        codes = procs.stop_all()
    wall = time.monotonic() - t0
    for name, code in codes.items():
        if code not in (0, None) and not any(f.startswith(name) for f in failed):
            failed.append(f"{name} (exit code {code})")

    print(f"\n=== main job report ({wall:.1f} s wall) ===")
    if summary_file.is_file():
        s = json.loads(summary_file.read_text())
        print(format_sim_summary(s, brake_reasons(logs / "zone_controller.log")))
    else:
        failed.append("simulator summary missing")
    if bag.exists():
        ran = [LEGEND[n] for _, _, n, _ in consumers if n in LEGEND]
        if ran:
            print("estimators: " + "; ".join(ran))
        title = f"{args.scenario} seed {sc.seed}"
        check = subprocess.run([sys.executable, "-m", "train_estimation.tools.check_bag", str(bag),
                                "--out", str(out / "check"), "--line", str(line_file),
                                "--rate-factor", str(args.rate_factor), "--title", title],
                               text=True, capture_output=True)
        print(check.stdout)
        if check.returncode != 0:
            failed.append(f"check_bag (exit {check.returncode}: {check.stderr.strip()[-300:]})")
    print(f"outputs: {out}")
    if failed:
        print("FAILED: " + "; ".join(failed))
        return 1
    print("all processes ran and stopped cleanly")
    return 0


def brake_reasons(log: Path) -> list[str]:
    """Distinct reasons the zone controller gave for setting the emergency brake (its log)."""
    if not log.is_file():
        return []
    seen = []
    for line in log.read_text(errors="replace").splitlines():
        m = re.search(r"emergency brake SET(?: \([a-z_]+\))?:(.*)", line)
        if m:  # the zone controller logs "emergency brake SET (state): reason"
            why = re.sub(r"\d+\.\d+", "#", m.group(1).strip())
            if why not in seen:
                seen.append(why)
    return seen


def format_sim_summary(s: dict, reasons: list[str] = ()) -> str:
    lines = [f"scenario {s.get('scenario')} seed {s.get('seed')}: {s.get('t_end', 0):.0f} s "
             f"simulated"]
    stops = s.get("stops", [])
    if stops:
        lines.append(f"stations served: {len(stops)}")
        lines.append("  station          stopping error (m, + = overshoot)")
        for st in stops:
            lines.append(f"  {st['station']:<16} {st['stopping_error']:+8.2f}")
    else:
        lines.append("stations served: 0")
    startup = int(s.get("startup_emergency_brakes", 0))
    incidents = int(s.get("emergency_brakes", 0)) - startup
    lines.append(f"emergency brakes: {incidents} during the run (incidents)")
    if startup:
        lines.append("  + start-up: the train starts braked until the zone controller's first "
                     "movement authority,\n    which needs a position report (expected, not an "
                     "incident); released at departure")
    if reasons:
        lines.append("  the zone controller set the brake for (its log): " + "; ".join(reasons))
    for topic, d in s.get("link", {}).items():
        lines.append(f"{topic}: {d['sent']} sent, {d['dropped']} dropped "
                     f"({d['received_fraction']:.3f} received)")
    return "\n".join(lines)


if __name__ == "__main__":
    sys.exit(main())
