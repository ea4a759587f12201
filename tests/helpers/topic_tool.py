"""A tiny stand-in for `ros2 topic pub/echo` (there is no ros2cli on the pip set-up).

    python topic_tool.py pub  TYPE TOPIC MESSAGES.json   # publish, once a subscriber matched
    python topic_tool.py echo TYPE TOPIC OUT.jsonl        # write every message as a JSON line

TYPE is a train_interfaces message name (TrainState, ...). Runs until SIGINT/SIGTERM.
"""

import argparse
import json
import sys

from train_core.ros import dict_to_msg, msg_class, msg_to_dict, parse_cli, run_node


def main(argv=None) -> int:
    def extra(p: argparse.ArgumentParser) -> None:
        p.add_argument("mode", choices=["pub", "echo"])
        p.add_argument("type")
        p.add_argument("topic")
        p.add_argument("file")

    args, ros_args = parse_cli("publish or echo train_interfaces messages", argv, extra)

    def factory():
        from rclpy.node import Node
        from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

        cls = msg_class(args.type)
        # Reliable + transient-local: a reader that matches a moment later still gets every
        # message, so nothing depends on timing once discovery has matched the two sides.
        qos = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL)

        class Tool(Node):
            def __init__(self):
                super().__init__(f"topic_tool_{args.mode}")
                if args.mode == "pub":
                    with open(args.file) as fh:
                        self.todo = [dict_to_msg(d, cls()) for d in json.load(fh)]
                    self.pub = self.create_publisher(cls, args.topic, qos)
                    self.timer = self.create_timer(0.05, self.tick)
                else:
                    self.out = open(args.file, "w")
                    self.create_subscription(cls, args.topic, self.on_msg, qos)

            def tick(self):
                # Publish only once discovery matched a subscriber: no blind sleeping.
                if self.todo and self.pub.get_subscription_count() > 0:
                    for m in self.todo:
                        self.pub.publish(m)
                    self.todo = []

            def on_msg(self, msg):
                self.out.write(json.dumps(msg_to_dict(msg)) + "\n")
                self.out.flush()

            def close(self):
                if args.mode == "echo":
                    self.out.close()

        return Tool()

    return run_node(factory, ros_args)


if __name__ == "__main__":
    sys.exit(main())
