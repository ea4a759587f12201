"""The ROS layer shared by `robust_filter` and `gsma_estimator`: :class:`EstimatorNode`
(its parameters and models, without rclpy: :mod:`.estimator_params`).

Callbacks push the message (with every input message already received, in the order they were
sent: :meth:`EstimatorNode._take_in_order`) with its arrival time on the node's clock into the
runner (``EstimatorRunner.push``) and at once advance the runner to its ready time, so that an
odometer sample's estimate is published as soon as the sample (and the command of its cycle) is
in; a steady wall-clock timer (``tick_period``) publishes the slots the clock alone makes due:
a lost sample's predicted slot once it is ``slot_grace`` overdue (``EstimatorRunner.tick``),
except on simulated time (``use_sim_time``), where the inputs' watermarks alone publish the
slots. Each estimate is a TrainState stamped with its sample's own stamp (the odometer's
clock). Rejected input is logged with its reason (throttled; names of ``core/reasons.py``) and
counted; events (a sequence reset, separate clocks found) are logged once each; the counts are
logged at shutdown.

Besides the TrainState, each estimate is published as ``nav_msgs/Odometry`` on ``odom/<name>``
(``estimate/robust`` -> ``odom/robust``; covariances by ``core/online/odometry.py``), and the node's
health (input rates, accepted and rejected counts by reason, staleness, latency, integrity) goes
to ``/diagnostics`` once per ``diagnostics_period`` (levels by ``train_core.diagnostics``).
"""

from __future__ import annotations

import math
import time
from collections import deque
from collections.abc import Callable

from nav_msgs.msg import Odometry
from rclpy.clock import Clock, ClockType
from rclpy.exceptions import InvalidHandle
from rclpy.node import Node
from train_core import diagnostics as D
from train_core.realtime import CallbackTrace, collect_due, settle_heap
from train_core.ros import Diagnostics, ParameterError, declare_config, sec_to_stamp, stamp_to_sec

from train_estimation.core.online.odometry import odometry_covariances
from train_estimation.core.online.runner import EstimatorRunner
from train_estimation.nodes.estimate_cdr import EstimateCdr, node_messages
from train_estimation.nodes.estimator_params import declare_common, load_models
from train_interfaces.msg import (
    BaliseReading,
    ControlCommand,
    OdometerReading,
    TrainState,
)

EVENT_LOG_PERIOD = 2.0  # s (steady), at most one log line per kind of event in this time
FIELDS: dict[str, Callable] = {  # an input message's fields, as EstimatorRunner.push takes them
    "odometer": lambda m: {"seq": m.seq, "distance": m.distance, "speed": m.speed,
                           "speed_variance": m.speed_variance},
    "balise": lambda m: {"seq": m.seq, "balise_id": m.balise_id, "position": m.position,
                         "position_variance": m.position_variance},
    "control": lambda m: {"target_acceleration": m.target_acceleration},
}


def _steady() -> float:
    """s, now on the steady clock: rclpy's (rcutils') steady clock is CLOCK_MONOTONIC, which
    ``time.monotonic_ns`` reads without building an rclpy Time (4 us each, read five times
    between a reading's arrival and its estimate)."""
    return time.monotonic_ns() * 1e-9


def _waiting(sub) -> list:
    """(message, MessageInfo) of every message ``sub`` has received and not yet given out, by
    rclpy's own take (the executor's take then finds none and skips); none once the
    subscription is destroyed at shutdown (InvalidHandle, which the executor skips too)."""
    out = []
    try:
        with sub.handle:
            while (taken := sub.handle.take_message(sub.msg_type, sub.raw)):
                out.append(taken)
    except InvalidHandle:
        pass
    return out


def _quantiles(values: list[float]) -> tuple[float, float, float]:
    """(p50, p99, max) of a non-empty list, order statistics as in the benchmarks' tables."""
    v = sorted(values)
    return v[len(v) // 2], v[min(len(v) - 1, int(0.99 * len(v)))], v[-1]


def fill_state(msg, out) -> None:
    """A runner ``Output`` into a TrainState (filled in place: a node keeps one message object,
    and publish copies it out)."""
    sec_to_stamp(out.stamp, msg.header.stamp)
    msg.position, msg.velocity = out.position, out.velocity
    msg.acceleration, msg.braking_rate = out.acceleration, out.braking_rate
    msg.covariance = out.covariance
    msg.measurement_used = out.measurement_used
    msg.integrity = out.integrity
    msg.protection_level_ahead = out.protection_level_ahead
    msg.protection_level_behind = out.protection_level_behind


def fill_odometry(odom, state, risk: float) -> None:
    """A TrainState as nav_msgs/Odometry, in place (frames and covariances:
    core/online/odometry.py; ``risk`` the integrity risk its levels are stated at)."""
    odom.header.stamp = state.header.stamp
    odom.pose.pose.position.x = state.position
    odom.twist.twist.linear.x = state.velocity
    odom.pose.covariance, odom.twist.covariance = odometry_covariances(
        state.covariance, (state.protection_level_ahead, state.protection_level_behind, risk))


class EstimatorNode(Node):
    """A node that feeds ``make_adapter(node, train, line, start, common)`` through a runner
    (``name``: the node's name; ``topic``: where its estimates go, e.g. ``estimate/robust``)."""

    def __init__(self, name: str, topic: str, make_adapter: Callable):
        super().__init__(name)
        common = declare_common(self)
        train, line, start = load_models(common)
        try:
            self.adapter = make_adapter(self, train, line, start, common)
        except ValueError as exc:
            raise ParameterError(str(exc)) from None
        try:
            from train_estimation.core.online.integrity import IntegrityParams

            integrity = declare_config(self, IntegrityParams)
        except ValueError as exc:
            raise ParameterError(str(exc)) from None
        try:
            self.runner = EstimatorRunner(self.adapter, 1.0 / common["odometer_rate"],
                                          control_clock=common["control_clock"],
                                          count_clock=common["count_clock"],
                                          max_future=common["max_future"],
                                          slot_grace=common["slot_grace"],
                                          integrity=integrity, fail_safe=True)
        except ValueError as exc:
            raise ParameterError(f"parameter control_clock: {exc}") from None
        self.n_events = 0
        self.failure_logged = False  # the runner's failure (fail_safe) said in the log
        self.rate_warned = False  # the odometer_rate warning logged (diagnostics)
        self.arrived: dict[float, float] = {}  # odometer stamp -> arrival (steady s)
        # s, odometer received -> its estimate published, in the steady state and in the
        # start-up (the runner starts on the third sample and judges each clock's stamps
        # once min_judged have arrived: those first samples wait by design)
        self.latency: list[float] = []
        self.latency_startup: list[float] = []
        # the steady-state latency split: waiting for the cycle's other inputs (the runner
        # releases a sample once the control watermark passes it) and processing (the
        # runner's work and publishing, from the start of the tick that released it)
        self.waited: list[float] = []
        self.processed: list[float] = []
        self.separate_logged = False
        self.delay = common["output_delay"]
        self.wait_subs = common["wait_for_subscribers"]
        self.pub = self.create_publisher(TrainState, topic, 1000)
        self.odom_topic = "odom/" + topic.rsplit("/", 1)[-1]
        self.odom_pub = self.create_publisher(Odometry, self.odom_topic, 1000)
        # An estimate's two messages are written as bytes from templates of the node's own
        # (estimate_cdr: the same messages; 12 us an estimate at the median with both
        # published, against 34 us filled and converted by rclpy: ./run bench publish). The
        # messages themselves, with the fields that never change set, are built once and
        # refilled only for a stamp the templates leave to rclpy (_publish)
        self.cdr = EstimateCdr(self.adapter.source)
        self._state_msg, self._odom_msg = node_messages(self.adapter.source)
        # /diagnostics: counters the runner does not keep (arrivals), read by the core
        self.started = _steady()
        self.received = dict.fromkeys(("odometer", "control", "balise"), 0)
        self.last_arrival = dict.fromkeys(self.received, math.nan)
        self.window_latency: list[float] = []
        self.last_integrity: tuple | None = None  # (label, doubts, PL ahead, PL behind)
        self.n_published = 0
        self.diag = Diagnostics(self, f"{self.adapter.source} estimator",
                                D.EstimatorThresholds, self.diagnostics)
        # The inputs in the order they were sent (_take_in_order): rclpy's executor takes the
        # messages that are ready together in the order these subscriptions were made
        self.inputs = (
            ("control", self.create_subscription(ControlCommand, "control",
                                                 self.on_control, 2000)),
            ("odometer", self.create_subscription(OdometerReading, "odometer",
                                                  self.on_odometer, 2000)),
            ("balise", self.create_subscription(BaliseReading, "balise", self.on_balise, 200)))
        # ... and on simulated time the world's /clock before them (rclpy's own subscription,
        # made with the node: _take_in_order)
        self.clock_in = next(((sub, sub.callback) for sub in self.subscriptions
                              if sub.topic_name == "/clock"), None)
        # Every message ticks the runner itself (outputs are released by the inputs'
        # watermarks); the timer covers what only the clock can tell: a lost reading's
        # slot, published once it is slot_grace overdue (EstimatorRunner.tick; with a 1 Hz
        # odometer the next message comes a second later), silence on every input (a dead
        # link: the node's clock then stands in for the commands) and discovery. 20 Hz
        # (tick_period) is enough for that and leaves the cores to the callbacks (200 Hz
        # made no latency difference); the replays tick at the same period.
        self.timer = self.create_timer(common["tick_period"], self.tick,
                                       clock=Clock(clock_type=ClockType.STEADY_TIME))
        # On simulated time (use_sim_time) the steady timer says nothing about the stamps:
        # the world runs at rate_factor x wall time and is paced by the estimates, so a
        # reading "overdue" on the steady clock is one still queued behind a command or a
        # /clock (a loaded node), and the timer's phase decided whether its slot left as a
        # prediction, before the commands of its cycle (two runs of one scenario and seed
        # would publish different estimates). There the slots follow the inputs' watermarks
        # alone: the simulator's next messages publish a lost reading's slot.
        self.clock_slots = not self.get_parameter("use_sim_time").value
        self.waiting: list = []  # messages received before a simulated clock started
        self.ros_last = 0  # ns, the ROS clock's last reading seen (simulated time)
        self.ticks: deque = deque(maxlen=64)  # s, its recent steps (arrival resolution)
        self.n_reported = 0
        self.event_log: dict = {}  # (kind, event) -> (steady s last logged, not logged since)
        self.get_logger().info(
            f"{self.adapter.source} on {line.name} / {train.name}, start at "
            f"{start.position:.1f} m, output {common['odometer_rate']:g} Hz on "
            f"'{self.pub.topic_name}' and '{self.odom_pub.topic_name}' (remappings applied)")
        # start-up's objects out of every later garbage collection (train_core.realtime)
        settle_heap()
        # where the callbacks' time goes, live (off unless TRAIN_NODE_TRACE names a directory:
        # train_core.realtime.CallbackTrace, benchmarks/bench_latency.py --trace)
        self.trace = CallbackTrace.from_env()
        if self.trace:
            self.trace.wrap(self)

    def _arrival(self) -> float | None:
        """s, now on the receive clock the runner judges stamps against (the contract's
        reference clock, which is the log time of a bag): the steady clock; on simulated
        time (use_sim_time) the ROS clock, the world's /clock (the simulator's, or a
        player's: the bag's log time). On the steady clock a simulation at 10x real time
        runs its stamps ten times faster than their arrivals, which no stream clock is (the
        default ``control_clock: auto`` refused 3,892 of 3,900 commands as stamped ahead).
        None while the simulated clock has not started. Waiting (a command stream's
        silence, EstimatorRunner.ready_time) stays on the steady clock: at 20x a stall of
        150 ms is 3 s of simulated time, and judged there it let the readings run ahead of
        commands that were only queued."""
        if self.clock_slots:
            return _steady()
        t = self.get_clock().now().nanoseconds
        if t <= 0:
            return None
        if t != self.ros_last:  # /clock ticked: its step is how finely arrivals are timed
            if self.ros_last:
                self.ticks.append((t - self.ros_last) * 1e-9)
                self.runner.arrival_resolution = max(self.ticks)
            self.ros_last = t
        return t * 1e-9

    def _push(self, kind: str, msg, fields: dict) -> None:
        recv = self._arrival()
        wall = _steady()
        if recv is None:  # before the first /clock: held, pushed when it starts
            self.waiting.append((kind, msg, fields, wall))
            return
        held, self.waiting = self.waiting, []
        for k, m, f, w in held:
            self._push_one(k, m, f, recv, w)
        self._push_one(kind, msg, fields, recv, wall)
        if self.trace:
            self.trace.mark("pushed")
        self.tick()

    def _push_one(self, kind: str, msg, fields: dict, recv: float, wall: float) -> None:
        stamp = stamp_to_sec(msg.header.stamp)
        self.received[kind] += 1
        self.last_arrival[kind] = wall
        reason = self.runner.push(kind, stamp, fields, recv, wall=wall)
        if kind == "odometer" and not reason:
            self.arrived[stamp] = wall  # for the received -> published latency
            if self.trace:
                self.trace.mark("reading", stamp)

    def _log_event(self, kind: str, stamp: float, text: str, now: float,
                   warn: bool = False, what: str | None = None) -> None:
        """One line per event (``warn``: per input refused), but at most one per kind of
        event and input every EVENT_LOG_PERIOD s (a lagging node fuses hundreds of readings
        late in a row): the next line says how many were not logged (all are counted in
        /diagnostics)."""
        key = (kind, what or text.split(":", 1)[0])
        last, quiet = self.event_log.get(key, (-math.inf, 0))
        if now - last < EVENT_LOG_PERIOD:
            self.event_log[key] = (last, quiet + 1)
            return
        more = f" ({quiet} more like it not logged)" if quiet else ""
        # one call site per severity: rclpy's logger refuses a call site whose severity
        # changes between calls (ValueError in the callback: the node died)
        line = f"{kind} at {stamp:.3f} s: {text}{more}"
        if warn:
            self.get_logger().warning(line)
        else:
            self.get_logger().info(line)
        self.event_log[key] = (now, 0)

    def on_odometer(self, msg, info) -> None:
        self._take_in_order("odometer", msg, info)

    def on_balise(self, msg, info) -> None:
        self._take_in_order("balise", msg, info)

    def on_control(self, msg, info) -> None:
        self._take_in_order("control", msg, info)

    def _take_in_order(self, kind: str, msg, info) -> None:
        """Push ``msg`` and every input message already received, in the order they were sent.

        rclpy's executor takes the messages that are ready together one per subscription, in
        the order the subscriptions were made, whatever order they were sent in. The runner's
        output depends on that order where a reading is stamped before a slot its cycle's
        command releases (a balise read 30 ms before an odometer slot and sent just before
        the slot's command: pushed first it is in that slot's estimate, pushed after the
        command it is fused late, into the next ones). A node that had waited a moment then
        published what a replay of the same messages in their order does not. So each
        callback takes every input message already waiting (the executor's own take: one it
        finds taken is skipped) and pushes them by their writer's source timestamp, each
        followed by its tick as if it had come alone: the node's arrival order is the order
        sent, on a loaded machine as on an idle one. A simulator or a player publishes all
        inputs from one process, so that order is theirs; between producers on two machines
        it is only as good as their clocks' agreement, over messages that arrived together
        anyway. Ties (and a middleware without source timestamps, 0) keep the take order.

        On simulated time a /clock that came is taken first, as the executor takes it before
        the inputs it finds with it (rclpy made that subscription with the node): each input
        is timed by the latest /clock the node has, never by one from before its own step.
        The /clock queue keeps one message, so under load the clocks between are lost, and
        an input timed by the last one applied before it was sent would look ahead of its
        stream by the steps lost (the step watch refuses a lone balise that far ahead)."""
        if self.clock_in is not None:
            sub, apply = self.clock_in
            for m, _ in _waiting(sub):
                apply(m)  # the node's ROS clock set, as rclpy's callback does
        got = [(info["source_timestamp"], 0, kind, msg)]
        for k, sub in self.inputs:
            got += [(i["source_timestamp"], len(got) + j, k, m)
                    for j, (m, i) in enumerate(_waiting(sub))]
        if len(got) > 1:
            got.sort(key=lambda g: g[:2])
        for _, _, k, m in got:
            self._push(k, m, FIELDS[k](m))

    def tick(self) -> None:
        now = self._arrival()  # the arrival clock (see _arrival)
        if now is None:
            if self.waiting and _steady() - self.waiting[0][3] > 2.0:
                self.get_logger().warning(
                    f"use_sim_time is set and no /clock has arrived: {len(self.waiting)} "
                    "messages held until one does (publish /clock, or run without "
                    "use_sim_time)", throttle_duration_sec=5.0)
            return
        if self.wait_subs:  # discovery, as the simulator's wait_for_subscribers: readers
            matched = self.pub.get_subscription_count()
            if matched < self.wait_subs:  # that match late would miss the first estimates
                self.get_logger().info(  # (inputs stay queued meanwhile)
                    f"waiting for subscribers: {self.pub.topic_name} {matched} of "
                    f"{self.wait_subs}; estimates held until they match",
                    throttle_duration_sec=10.0)
                return
            self.wait_subs = 0
        # Outputs wait for the inputs' watermarks (or 4 x delay for a lost sample), so the
        # node computes exactly what the offline replay of the same messages computes; a
        # slot whose reading is overdue on the arrival clock leaves by runner.tick.
        t_tick = _steady()
        trace = self.trace
        if trace:
            trace.mark("tick")
        outs = self.runner.advance_to(self.runner.ready_time(now, self.delay,
                                                              4 * self.delay, wall=t_tick))
        if trace:
            trace.mark("advanced")
        self._publish(outs, t_tick)
        if self.clock_slots:
            # the slots the arrival clock alone makes due, once what the inputs released is
            # out (a reading's estimate does not wait for this check; the same estimates in
            # the same order)
            self._publish(self.runner.tick(now), t_tick)
        if len(self.arrived) > 1000:  # samples that never became an estimate (refused)
            self.arrived.clear()
        if self.runner.failure and not self.failure_logged:
            self.failure_logged = True
            self.get_logger().error(
                f"the estimator failed ({self.runner.failure}); every estimate from here on "
                "is ALARM and no input is fused: restart the node (a defect: please report "
                f"this log)\n{self.runner.failure_trace}")
        events = sum(self.runner.events.values())
        if events > self.n_events:  # accepted input worth a line each (seq reset, ...)
            for kind, stamp, text in self.runner.last_events[-(events - self.n_events):]:
                self._log_event(kind, stamp, text, t_tick)
            self.n_events = events
        if self.runner.separate_clocks and not self.separate_logged:
            self.separate_logged = True
            self.get_logger().info("control is stamped on another clock than the odometer: "
                                   "mapped onto the odometer's clock (drift "
                                   f"{self.runner.drift:.2e} so far): {self.runner.separate_why}")
        total = sum(self.runner.rejected.values())
        if total > self.n_reported:  # the door or the core refused input: say why, once
            # (the runner keeps the last 20 reasons; every one is counted in /diagnostics)
            fresh = self.runner.last_reasons[-min(total - self.n_reported, 20):]
            self.n_reported = total
            for kind, stamp, why in fresh:
                self._log_event(kind, stamp, f"rejected: {why} ({total} rejected so far)",
                                t_tick, warn=True, what="rejected " + why.split(":", 1)[0])
        # the state a late reading would rewind to, copied now that the estimates are out
        # rather than between the next reading's arrival and its estimate
        # (EstimatorRunner.settle), and the garbage collection the allocations made due,
        # rather than inside the next callback before its estimate (train_core.realtime)
        self.runner.settle()
        collect_due()

    def _publish(self, outs: list, t_tick: float) -> None:
        """Publish the estimates (TrainState and Odometry) and note their latency (``t_tick``:
        s, the steady clock when the tick that released them began)."""
        trace = self.trace
        for out in outs:
            raw = self.cdr.encode(out, self.runner.integrity.integrity_risk)
            if raw is not None:
                self.pub.publish(raw[0])
                self.odom_pub.publish(raw[1])
            else:  # a stamp beyond int32 seconds: rclpy's messages, as they make it
                msg = self._state_msg  # one message object, filled anew (publish copies it)
                fill_state(msg, out)
                self.pub.publish(msg)
                self.odom_pub.publish(self._odometry(msg))
            if trace:
                trace.mark("published", out.stamp)
            self.n_published += 1
            self.last_integrity = (int(out.integrity),
                                   str(getattr(out, "integrity_reason", "")),
                                   out.protection_level_ahead, out.protection_level_behind)
            t_recv = self.arrived.pop(out.stamp, None)
            if t_recv is not None:
                lat = _steady() - t_recv
                startup = len(self.latency) + len(self.latency_startup) < \
                    self.runner.min_judged + 3
                if startup:
                    self.latency_startup.append(lat)
                else:
                    self.latency.append(lat)
                    self.window_latency.append(lat)
                    self.waited.append(max(0.0, t_tick - t_recv))
                    self.processed.append(lat - self.waited[-1])

    def _odometry(self, state):
        """The estimate as nav_msgs/Odometry (frames and covariances:
        core/online/odometry.py), in the node's one Odometry object (publish copies it out)."""
        fill_odometry(self._odom_msg, state, self.runner.integrity.integrity_risk)
        return self._odom_msg

    def diagnostics(self):
        """The node's Status for /diagnostics (the rules: train_core.diagnostics)."""
        now = _steady()
        inputs = []
        for kind in ("odometer", "control", "balise"):
            reasons = {k.split(":", 1)[1]: n for k, n in self.runner.rejected.items()
                       if k.split(":", 1)[0] == kind}
            inputs.append(D.InputCounts(kind, self.received[kind],
                                        self.runner.accepted.get(kind, 0), reasons,
                                        self.last_arrival[kind],
                                        watch_stale=kind != "balise"))
        checks, values = self.diag.input_checks(now, self.started, inputs)
        lat_checks, lat_values = D.latency_check(self.window_latency, self.diag.cfg)
        # (a failed runner's state is not asked: the failure is the check, below)
        rate_checks, rate_values = ([], []) if self.runner.failure else \
            D.rate_check(self.runner.sample_period(), self.runner.period)
        if rate_checks and not self.rate_warned:  # once in the log; /diagnostics each time
            self.get_logger().warning(rate_checks[0][1])
            self.rate_warned = True
        self.window_latency = []
        integ = self.last_integrity
        i_checks, i_values = D.integrity_check(*(integ if integ else (None, "")))
        extra = [("source", self.adapter.source), ("estimates_published",
                                                   str(self.n_published))]
        if self.runner.failure:  # the adapter's state is not trusted (nor asked) any more
            return D.combine(checks + lat_checks + rate_checks + i_checks
                             + [(D.ERROR, f"estimator failed: {self.runner.failure}")],
                             extra + values + lat_values + rate_values + i_values
                             + [("failure", self.runner.failure)])
        scale = self.adapter.odometer_scale()
        if scale is not None:  # what a next run can start from (parameter odometer_scale)
            extra += [("odometer_scale", f"{scale[0]:.6f}"),
                      ("odometer_scale_std", f"{scale[1]:.2e}")]
        for kind, n in sorted(self.runner.unstated.items()):
            # readings whose variance 0 was read as not stated (train.yaml's used)
            extra.append((f"{kind}.variance_unstated", str(n)))
        for kind, n in sorted(self.runner.uncounted.items()):
            # readings of a stream without a sample counter (seq never moves)
            extra.append((f"{kind}.seq_unstated", str(n)))
        if self.runner.unstamped:  # commands stamped 0, taken at their arrival
            extra.append(("control.stamp_unstated", str(self.runner.unstamped)))
        lat = self.adapter.balise_latency()
        if lat is not None:  # a reader that stamps late: the fixes are moved by v tau
            extra += [("balise_latency", f"{lat[0]:.3f}"),
                      ("balise_latency_std", f"{lat[1]:.3f}")]
        return D.combine(checks + lat_checks + rate_checks + i_checks,
                         extra + values + lat_values + rate_values + i_values)

    def close(self) -> None:
        if self.trace:
            self.get_logger().info(f"callback trace written to "
                                   f"{self.trace.dump(self.get_name())}")
        if self.latency:
            p50, p99, top = _quantiles(self.latency)
            w50, w99, _ = _quantiles(self.waited)
            c50, c99, _ = _quantiles(self.processed)
            self.get_logger().info(f"latency odometer received -> estimate published: "
                                   f"p50 {1e3 * p50:.2f} ms, p99 {1e3 * p99:.2f} ms, "
                                   f"max {1e3 * top:.2f} ms over {len(self.latency)} samples"
                                   f" (steady state; start-up: max "
                                   f"{1e3 * max(self.latency_startup, default=0.0):.2f} ms "
                                   f"over the first {len(self.latency_startup)}); waiting "
                                   f"for inputs p50 {1e3 * w50:.2f} ms, p99 {1e3 * w99:.2f} "
                                   f"ms; processing p50 {1e3 * c50:.2f} ms, p99 "
                                   f"{1e3 * c99:.2f} ms")
        self.get_logger().info(f"accepted {dict(self.runner.accepted)}; "
                               f"rejected {dict(self.runner.rejected) or 'none'}; "
                               f"events {dict(self.runner.events) or 'none'}")
        self.get_logger().info(f"clocks: {self.runner.clock_summary()}")
        if self.runner.failure:
            self.get_logger().error(f"the estimator had failed: {self.runner.failure}")
            return
        scale = self.adapter.odometer_scale()
        if scale is not None:
            self.get_logger().info(f"odometer's scale learnt from the balises: "
                                   f"{scale[0]:.6f} +- {scale[1]:.1e} (reading / true "
                                   "distance; a next run of this train can start from it: "
                                   "parameter odometer_scale)")
        lat = self.adapter.balise_latency()
        if lat is not None:
            self.get_logger().info(f"balise reader's latency learnt from the balises: "
                                   f"{lat[0]:.3f} +- {lat[1]:.3f} s (its stamp minus the "
                                   "time the train passed the balise)")
