"""`ZoneControllerNode`: each train's TrainState reports checked and handed to the pure
`train_sim.zone.ZoneController`, its movement authorities published at `rate` and at once on an
alarm. Parameters and command line: `zone_controller.py`, which imports this module (rclpy with
it) when it starts the node."""

from __future__ import annotations

import math
import re
from dataclasses import replace

from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from train_core import diagnostics as D
from train_core.model import load_line
from train_core.ros import (
    Diagnostics,
    ParameterError,
    declare_config,
    stamp_to_sec,
)

from train_interfaces.msg import MovementAuthority, TrainState
from train_sim.zone import (
    ALARM,
    RefusalLog,
    TrainReport,
    ZoneController,
    ZoneNodeConfig,
    ZoneParams,
)


class ZoneControllerNode(Node):
    def __init__(self):
        super().__init__("zone_controller")

        try:
            params = declare_config(self, ZoneParams)
            node_cfg = declare_config(self, ZoneNodeConfig)
        except ValueError as exc:
            raise ParameterError(str(exc)) from None
        trains, state_topic = list(node_cfg.trains), node_cfg.state_topic
        line_file, danger, rate = node_cfg.line_file, node_cfg.danger_points, node_cfg.rate
        points = [p for p in danger if p >= 0]
        if line_file:
            try:
                line = load_line(line_file)
            except Exception as exc:  # ConfigError: already a one-line reason
                raise ParameterError(str(exc)) from None
            points.append(line.length)
        length = line.length if line_file else math.inf
        self.zone = ZoneController(replace(params, danger_points=tuple(points),
                                           line_length=length), fail_safe=True)
        self.failure_logged = False
        self.trains = [self._train_id(t) for t in trains]
        self.pubs = {}
        for ns, tid in zip(trains, self.trains):
            prefix = f"{ns.rstrip('/')}/" if ns else ""
            self.create_subscription(
                TrainState, f"{prefix}{state_topic}",
                lambda msg, tid=tid: self.on_state(tid, msg), 50)
            self.pubs[tid] = self.create_publisher(
                MovementAuthority, f"{prefix}movement_authority", 10)
        self.msg_type = MovementAuthority
        self.last_state: dict[str, str] = {}
        self.refusals = RefusalLog(node_cfg.log_interval)
        self.timer = self.create_timer(1.0 / rate, self.publish)
        # /diagnostics: per train, reports received (steady clock) and refused by reason
        self.steady = Clock(clock_type=ClockType.STEADY_TIME)
        self.started = self.steady.now().nanoseconds * 1e-9
        self.received = dict.fromkeys(self.trains, 0)
        self.refused: dict[str, dict[str, int]] = {t: {} for t in self.trains}
        self.last_arrival = dict.fromkeys(self.trains, math.nan)
        self.last_auth: dict = {}
        self.diag = Diagnostics(self, "movement authorities", D.InputThresholds,
                                self.diagnostics)
        self.get_logger().info(
            f"zone controller for {self.trains} on '{state_topic}', "
            f"danger points {points}, integrity risk {params.integrity_risk:g}")

    def _train_id(self, ns: str) -> str:
        if not ns:
            return self.get_namespace()
        return ns if ns.startswith("/") else f"{self.get_namespace().rstrip('/')}/{ns}"

    def now(self) -> float:
        return self.get_clock().now().nanoseconds * 1e-9

    def on_state(self, tid: str, msg) -> None:
        cov = [float(c) for c in msg.covariance]
        exact = msg.source == "truth"
        if exact:  # its covariance is NaN (not estimated), read as 0
            cov = [0.0 if math.isnan(c) else c for c in cov]
        now = self.now()
        rep = TrainReport(
            t_received=now, stamp=stamp_to_sec(msg.header.stamp),
            position=float(msg.position), velocity=float(msg.velocity),
            var_position=cov[0], var_velocity=cov[5],
            braking_rate=float(msg.braking_rate), var_braking_rate=cov[15],
            measurement_used=bool(msg.measurement_used), cov_position_velocity=cov[1],
            cov_velocity_position=cov[4], integrity=int(msg.integrity), exact=exact,
            pl_ahead=float(msg.protection_level_ahead),
            pl_behind=float(msg.protection_level_behind))
        resets = self.zone.clock_resets.get(tid, 0)
        prev = self.zone.reports.get(tid)
        kind = self.zone.report(tid, rep)
        if self.zone.failure and not self.failure_logged:
            self._failed()
        self.received[tid] += 1
        self.last_arrival[tid] = self.steady.now().nanoseconds * 1e-9
        if kind:
            key = "_".join(re.findall(r"[a-z0-9]+", kind.lower()))  # a diagnostics key
            self.refused[tid][key] = self.refused[tid].get(key, 0) + 1
            n = self.refusals.note(tid, kind, now)
            if n:
                _, _, detail = self.zone.last_refusal
                self.get_logger().warning(
                    f"{tid}: {n} report(s) refused ({kind}) since last logged, "
                    f"{self.zone.rejected[kind]} in all; latest: {detail}")
            return
        if self.zone.clock_resets.get(tid, 0) != resets:
            self.get_logger().warning(
                f"{tid}: estimator clock reset followed: stamps now {rep.stamp:.3f} s "
                f"(the previous timeline ended at {prev.stamp:.3f} s)")
        if rep.integrity == ALARM and (prev is None or prev.integrity != ALARM):
            self.publish()  # brake now, not at the next tick

    def _failed(self) -> None:
        """The zone controller failed (an exception, latched by ZoneController.fail_safe):
        said once with its traceback, every train braked at once."""
        self.failure_logged = True
        self.get_logger().error(f"the zone controller failed ({self.zone.failure}): every "
                                "train's emergency brake is set and no report is read from "
                                "here on; restart the node (a defect: please report this log)\n"
                                f"{self.zone.failure_trace}")
        self.publish()

    def publish(self) -> None:
        now = self.now()
        auths = self.zone.authorities(now, self.trains)
        if self.zone.failure and not self.failure_logged:
            self._failed()
            return
        for auth in auths:
            msg = self.msg_type()
            msg.header.stamp = self.get_clock().now().to_msg()
            msg.header.frame_id = "track"
            msg.train_id = auth.train_id
            msg.end_of_authority = float(auth.end_of_authority)
            msg.permitted_speed = float(auth.permitted_speed)
            msg.emergency_brake = auth.emergency_brake
            self.pubs[auth.train_id].publish(msg)
            self.last_auth[auth.train_id] = auth
            if auth.state != self.last_state.get(auth.train_id, "ok"):
                # a change of state is logged once (the reason's numbers change at every
                # publication); rclpy wants one severity per call site: two calls
                if auth.reason:
                    self.get_logger().warning(f"{auth.train_id}: emergency brake SET "
                                              f"({auth.state}): {auth.reason}")
                else:
                    self.get_logger().info(f"{auth.train_id}: emergency brake released")
                self.last_state[auth.train_id] = auth.state

    def diagnostics(self):
        """Reports per train as inputs; an emergency brake set is WARN with its reason
        (the zone doing its job on a train it cannot bound, worth an operator's look)."""
        now = self.steady.now().nanoseconds * 1e-9
        inputs = [D.InputCounts(t, self.received[t],
                                self.received[t] - sum(self.refused[t].values()),
                                dict(self.refused[t]), self.last_arrival[t])
                  for t in self.trains]
        checks, values = self.diag.input_checks(now, self.started, inputs)
        for t in self.trains:
            auth = self.last_auth.get(t)
            values.append((f"{t}.emergency_brake", "unknown" if auth is None
                           else str(bool(auth.emergency_brake)).lower()))
            if auth is not None and auth.emergency_brake:
                checks.append((D.WARN, f"{t}: emergency brake set ({auth.reason})"))
            if auth is not None:
                values.append((f"{t}.end_of_authority_m", f"{auth.end_of_authority:.1f}"))
        return D.combine(checks, values)
