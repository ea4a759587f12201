"""An estimator node and a sender in one process, the node not spinning while a cycle's messages
are sent, so that they are all waiting when it next wakes (a loaded node).

    python arrival_order.py LINE_FILE TRAIN_FILE OUT.json

The train stands over the line's first balise; the odometer and the commands come at 10 Hz,
each cycle sent and then taken before the next, except that the balise, read 30 ms before the
slot at 5 s, is sent together with that slot's reading and command: balise, odometer, command,
in that order. Writes the robust filter's runner events and counts as JSON.
"""

import json
import sys
import time


def main(line_file: str, train_file: str, out: str) -> int:
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from train_core.model import load_line
    from train_core.ros import sec_to_stamp

    from train_estimation.nodes.estimator_node import EstimatorNode
    from train_estimation.nodes.robust_filter import make_adapter
    from train_interfaces.msg import BaliseReading, ControlCommand, OdometerReading

    balise = load_line(line_file).balises[0]
    t_balise = 4.97
    rclpy.init(args=["--ros-args", "-r", "__ns:=/arrival_order",
                     "-p", f"line_file:={line_file}", "-p", f"train_file:={train_file}",
                     "-p", f"initial_position:={balise.position}",
                     "-p", "control_clock:=same"])
    try:
        node = EstimatorNode("robust_filter", "estimate/robust", make_adapter)
        sender = rclpy.create_node("sender", namespace="/arrival_order")
        pubs = {"odometer": sender.create_publisher(OdometerReading, "odometer", 100),
                "balise": sender.create_publisher(BaliseReading, "balise", 100),
                "control": sender.create_publisher(ControlCommand, "control", 100)}
        executor = SingleThreadedExecutor()
        executor.add_node(node)
        end = time.monotonic() + 20.0
        while any(p.get_subscription_count() < 1 for p in pubs.values()):
            if time.monotonic() > end:
                raise TimeoutError("the node's subscriptions did not match")
            executor.spin_once(timeout_sec=0.05)

        def msg(kind: str, t: float):
            m = {"odometer": OdometerReading, "balise": BaliseReading,
                 "control": ControlCommand}[kind]()
            m.header.stamp = sec_to_stamp(t)
            if kind == "odometer":
                m.seq, m.distance, m.speed, m.speed_variance = round(10 * t), 0.0, 0.0, 0.01
            elif kind == "balise":
                m.seq, m.balise_id, m.position = 1, balise.id, balise.position
                m.position_variance = 1.0
            return m

        start = time.monotonic()
        for k in range(1, 81):
            t = 0.1 * k
            time.sleep(max(0.0, start + t - time.monotonic()))  # the sensors' 10 Hz
            sent = ["control", "odometer"] if abs(t - 5.0) > 1e-9 else \
                ["balise", "odometer", "control"]
            for kind in sent:
                pubs[kind].publish(msg(kind, t_balise if kind == "balise" else t))
            # all of the cycle's messages are in before the node wakes (the balise's cycle:
            # with time to spare on a loaded machine)
            time.sleep(0.02 if len(sent) == 2 else 0.3)
            # the node takes what waits (one message per subscription per wake), and its
            # callbacks' own work
            for _ in range(10):
                executor.spin_once(timeout_sec=0.002)
        runner = node.runner
        with open(out, "w") as f:
            json.dump({"events": dict(runner.events), "accepted": dict(runner.accepted),
                       "rejected": dict(runner.rejected)}, f)
        node.destroy_node()
        sender.destroy_node()
    finally:
        rclpy.try_shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main(*sys.argv[1:]))
