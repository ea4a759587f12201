"""`SimulatorNode`: steps the pure `train_sim.world.World` on a wall timer and publishes the
odometer, balise, control and ground-truth messages it emits, /clock and its diagnostics; hands
the movement authorities to the ATO. Its parameters (`SimulatorConfig`) and command line live in
`simulator.py`, which imports this module (and rclpy) only to start the node."""

from __future__ import annotations

import json
import math
import time
from pathlib import Path

from rclpy.clock import Clock as RosClock
from rclpy.clock import ClockType
from rclpy.node import Node
from rosgraph_msgs.msg import Clock
from train_core import diagnostics as D
from train_core.config import ConfigError
from train_core.ros import (
    TOPIC_TYPES,
    Diagnostics,
    ParameterError,
    declare_config,
    fields_to_msg,
    inputs_matched,
    msg_class,
    sec_to_stamp,
    stamp_to_sec,
    unacknowledged,
)

from train_interfaces.msg import MovementAuthority
from train_sim.nodes.simulator import PROGRESS, SimulatorConfig
from train_sim.scenario import load_scenario, with_model
from train_sim.summary import run_summary
from train_sim.world import World


class SimulatorNode(Node):
    def __init__(self):
        super().__init__("simulator")

        try:
            cfg = declare_config(self, SimulatorConfig)
        except ValueError as exc:
            raise ParameterError(str(exc)) from None
        scenario, model_dir, seed, duration = cfg.scenario, cfg.model, cfg.seed, cfg.duration
        self.rate_factor, self.step = cfg.rate_factor, cfg.wall_step
        self.clock_period, self.wait_log_period = cfg.clock_period, cfg.wait_log_period
        self.clock_said = -math.inf  # monotonic s of the last /clock
        self.exit_at_end, self.summary_file = cfg.exit_at_end, cfg.summary_file
        self.wait_subs, self.wait_truth = cfg.wait_for_subscribers, \
            cfg.wait_for_truth_subscribers
        self.publish_clock, self.start_at = cfg.publish_clock, cfg.start_at
        startup_eb, self.linger = cfg.start_with_emergency_brake, cfg.end_linger
        self.max_lead, pace_topics = cfg.max_lead, list(cfg.pace_topics)
        try:
            self.sc = load_scenario(scenario)
            if model_dir:
                self.sc = with_model(self.sc, model_dir)
        except ConfigError as exc:
            raise ParameterError(str(exc)) from None
        self.duration = self.sc.duration if duration < 0 else duration
        self.world = World(self.sc, None if seed < 0 else seed)
        if startup_eb:
            # No authority yet: the expected start-up state of a train under a zone
            # controller. Set here, at t = 0, not when the controller's first message happens
            # to arrive, so the run does not depend on discovery and wall-clock timing.
            self.world.set_movement_authority(-math.inf, 0.0, True)
        # deep queues: at 20x real time a subscriber that stalls for a second must not lose
        # samples (a lost control command would corrupt every estimator downstream)
        self.pubs = {t: self.create_publisher(msg_class(TOPIC_TYPES[t]), t, 2000)
                     for t in ("odometer", "balise", "control", "ground_truth")}
        self.clock_pub = self.create_publisher(Clock, "/clock", 10)
        self.create_subscription(MovementAuthority, "movement_authority", self.on_ma, 10)
        # Pacing (a lock-step co-simulation): a consumer that stalls for some wall time
        # (a loaded machine) holds the world back instead of seeing its data arrive late in
        # simulated time, where a zone controller would judge it stale and brake the train.
        self.paced = {}
        if self.max_lead > 0:
            for topic in pace_topics:
                self.paced[topic] = 0.0
                self.create_subscription(
                    msg_class(TOPIC_TYPES[topic]), topic,
                    lambda msg, topic=topic: self.on_paced(topic, msg), 100)
        self.last_wall = None
        self.counts = dict.fromkeys(self.pubs, 0)
        self.t_sim = 0.0
        # a log line every 5 % of the run (the main job draws its progress bar from them)
        self.report_step = self.duration / 20.0
        self.next_report = self.report_step
        self.wall0 = None
        # with readers waited for, the world goes on past its first messages once every
        # reader has acknowledged them (train_core.ros.unacknowledged)
        self.acked = not (self.wait_subs or self.wait_truth)
        self.waiting_since = None  # monotonic s since the world has stood waiting
        self.finished = False
        self.done = False
        self.timer = self.create_timer(self.step, self.tick)
        # /diagnostics: what the world receives (authorities, paced estimates); each input
        # is judged stale only once it has come (a world run without a zone controller is
        # a valid set-up, one that loses its controller is not)
        self.steady = RosClock(clock_type=ClockType.STEADY_TIME)
        self.started = self.steady.now().nanoseconds * 1e-9
        self.in_received = dict.fromkeys(["movement_authority", *self.paced], 0)
        self.in_last = dict.fromkeys(self.in_received, math.nan)
        self.ma_rejected: dict[str, int] = {}  # why -> authorities refused
        self.diag = Diagnostics(self, "train world", D.StaleThresholds, self.diagnostics)
        self.get_logger().info(
            f"scenario {self.sc.name}, seed {self.world.seed}, {self.duration:.0f} s at "
            f"{self.rate_factor:g}x real time")

    def _arrived(self, topic: str) -> None:
        self.in_received[topic] += 1
        self.in_last[topic] = self.steady.now().nanoseconds * 1e-9

    def diagnostics(self):
        now = self.steady.now().nanoseconds * 1e-9
        bad = {"movement_authority": self.ma_rejected}
        inputs = [D.InputCounts(t, n, n - sum(bad.get(t, {}).values()), bad.get(t, {}),
                                self.in_last[t], watch_stale=n > 0)
                  for t, n in self.in_received.items()]
        checks, values = self.diag.input_checks(now, self.started, inputs)
        state = ("waiting for subscribers" if self.wall0 is None
                 else "ended" if self.done else "running")
        head = [("scenario", self.sc.name), ("seed", str(self.world.seed)), ("state", state),
                ("sim_time_s", f"{self.t_sim:.2f}"), ("rate_factor", f"{self.rate_factor:g}")]
        head += [(f"{t}.published", str(n)) for t, n in self.counts.items()]
        return D.combine(checks, head + values)

    def on_ma(self, msg) -> None:
        self._arrived("movement_authority")
        why = self.world.set_movement_authority(msg.end_of_authority, msg.permitted_speed,
                                                msg.emergency_brake)
        if why:
            name = why.split(":")[0]
            self.ma_rejected[name] = self.ma_rejected.get(name, 0) + 1
            self.get_logger().warning(
                f"movement authority refused ({why}; the one in force kept"
                f"{', its emergency brake applied' if msg.emergency_brake else ''})",
                throttle_duration_sec=2.0)

    def on_paced(self, topic: str, msg) -> None:
        self._arrived(topic)
        self.paced[topic] = max(self.paced[topic], stamp_to_sec(msg.header.stamp))

    def _say_clock(self, now: float, due: bool = False) -> None:
        """/clock at the world's time when ``due`` (messages follow it) or when
        clock_period has passed since the last one (the timers of nodes on simulated
        time fire when it moves). Each /clock costs every node on simulated time a
        wake-up of its executor and rclpy's TimeSource callback, 0.6-0.8 ms of CPU
        (docs/benchmarks.md, Latency): at 100 Hz, more than the estimators' own
        callbacks."""
        if self.publish_clock and (due or now - self.clock_said >= self.clock_period):
            clock = Clock()
            sec_to_stamp(self.t_sim, clock.clock)
            self.clock_pub.publish(clock)
            self.clock_said = now

    def _say_waiting(self, now: float, what) -> None:
        """Log what the world waits for (``what()``, a line, or "" for nothing), once per
        wait_log_period of wall time that it waits: a run that stalls (a reader never
        matched, an estimator that stopped) names its cause in the simulator's log, which
        the main job reports. The line is made only when it is due (the world waits at
        many ticks of a paced run)."""
        if self.waiting_since is None:
            self.waiting_since = self.wait_said = now
        elif now - self.wait_said >= self.wait_log_period:
            self.wait_said = now
            line = what()
            if line:
                self.get_logger().info(
                    f"{line} ({now - self.waiting_since:.0f} s of wall time)")

    def _subscribers_short(self) -> str:
        return "waiting for subscribers: " + ", ".join(
            f"{t} {p.get_subscription_count()} of "
            f"{self.wait_truth if t == 'ground_truth' else self.wait_subs}"
            for t, p in self.pubs.items())

    def _paced_behind(self) -> str:
        behind = [f"{t} (newest stamp {s:.2f} s, {self.in_received[t]} received)"
                  for t, s in self.paced.items() if s + self.max_lead <= self.t_sim]
        return f"paced at t = {self.t_sim:.2f} s, waiting for " + ", ".join(behind) \
            if behind else ""  # (standing at the run's end waits for nothing)

    def tick(self) -> None:
        now = time.monotonic()
        if self.wall0 is None:
            # Discovery, not a blind sleep: recorders and estimators must be matched before
            # the first sample, or they would miss the start of the run.
            if not inputs_matched(self.pubs, self.wait_subs) or \
                    self.pubs["ground_truth"].get_subscription_count() < self.wait_truth:
                self._say_waiting(now, self._subscribers_short)
                return
            if self.start_at > 0:
                if time.time() < self.start_at:
                    return
                now -= time.time() - self.start_at  # the shared instant, not this tick
            self.wall0 = now
            self.waiting_since = None
        if not self.acked and any(self.counts.values()):
            late = unacknowledged(self.pubs)
            if late:  # the world stands, its clock said again, until every reader has them
                self._say_clock(now)
                self._say_waiting(now, lambda: "waiting for every reader to acknowledge the "
                                               "first messages on " + ", ".join(late))
                return
            waited = 0.0 if self.waiting_since is None else now - self.waiting_since
            self.get_logger().info(f"the first messages acknowledged by every reader "
                                   f"({waited * 1e3:.0f} ms waited)")
            self.acked, self.waiting_since = True, None
            # the wait is no simulated time (a shared start_at keeps its time base)
            if self.paced:
                self.last_wall = now
            elif not self.start_at:
                self.wall0 = now - self.t_sim / self.rate_factor
        if self.paced:  # advance by wall time elapsed, up to the slowest paced topic
            last, self.last_wall = self.last_wall or now, now
            target = min(self.t_sim + (now - last) * self.rate_factor,
                         min(self.paced.values()) + self.max_lead)
        else:
            target = (now - self.wall0) * self.rate_factor
        target = min(target, self.duration + self.linger)
        if target <= self.t_sim:
            # paced, waiting for the estimates: the world's clock stands still, and is said
            # again (each clock_period), so that a node whose /clock subscription matched
            # after the last tick
            # learns the time (a node on simulated time holds what it received until it
            # has a clock: under load the world waited for a node's estimates and the node
            # for a clock, and the run stopped)
            self._say_clock(now)
            if self.paced:
                self._say_waiting(now, self._paced_behind)
            return
        self.waiting_since = None
        if self.t_sim < self.duration:
            self.world.advance(min(target, self.duration))
        self.t_sim = target
        # the world's clock first, then what has arrived by it (with link latency, later
        # than it was sent): a node on simulated time receives each message at or after its
        # delivery time on the clock it judges stamps by, never before (latency >= 0)
        delivered = self.world.deliver(target)
        # and the run's last instant (duration + end_linger), which the nodes wait for
        self._say_clock(now, due=bool(delivered) or target >= self.duration + self.linger)
        for topic, stamp, fields in delivered:
            self.pubs[topic].publish(fields_to_msg(TOPIC_TYPES[topic], stamp, fields))
            self.counts[topic] += 1
        if not self.done and (self.t_sim >= self.next_report
                              or self.t_sim >= self.duration):
            self.get_logger().info(f"{PROGRESS} {min(self.t_sim, self.duration):.1f} of "
                                   f"{self.duration:.1f} s")
            while self.next_report <= self.t_sim:
                self.next_report += self.report_step
        if self.t_sim >= self.duration and not self.done:
            self.done = True
            self.get_logger().info(f"run ended at {self.duration:.1f} s; published "
                                   f"{self.counts}")
            if self.summary_file:
                summary = run_summary(self.world.result())
                summary["startup_emergency_brakes"] = self.world.driver.startup_emergency_brakes
                Path(self.summary_file).write_text(json.dumps(summary, indent=1))
        if self.done and self.t_sim >= self.duration + self.linger:
            self.finished = self.exit_at_end
