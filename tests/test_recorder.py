"""The recorder keeps what it received: clean stop and kill -9 mid-run."""

import signal

import pytest
from train_core.bagio import read_bag

pytestmark = pytest.mark.ros
NS = "/rec"


def _publish(ros_node, pub, cls, seqs):
    for s in seqs:
        msg = cls()
        msg.header.stamp.sec = 100 + s
        msg.seq = s
        msg.distance = 10.0 * s
        msg.speed = 1.0 + s
        msg.speed_variance = 0.01
        pub.publish(msg)
        ros_node.spin_for(0.01)


def _start(launch, ros_node, tmp_path, flush):
    from train_interfaces.msg import OdometerReading

    bag = tmp_path / "bag"
    proc = launch.node("train_estimation", "recorder", "--ros-args", "-r", f"__ns:={NS}",
                       "-p", f"bag:={bag}", "-p", f"flush_period:={flush}",
                       "-p", "topics:=[odometer]")
    pub = ros_node.node.create_publisher(OdometerReading, f"{NS}/odometer", 1000)
    ros_node.wait_until(lambda: pub.get_subscription_count() >= 1, 20, "the recorder to subscribe")
    return proc, pub, bag, OdometerReading


def test_clean_stop_keeps_everything(launch, ros_node, tmp_path):
    proc, pub, bag, cls = _start(launch, ros_node, tmp_path, 5.0)
    _publish(ros_node, pub, cls, range(40))
    ros_node.spin_for(1.0)
    assert launch.stop(proc) == 0, launch.logs()
    assert (bag / "metadata.yaml").exists()
    assert read_bag(bag).skipped == {}  # closed: indexed, nothing to say
    got = read_bag(bag).topics["odometer"]
    assert [f["seq"] for _, _, f in got] == list(range(40))
    assert all(f["distance"] == 10.0 * f["seq"] for _, _, f in got)


def test_kill_9_keeps_everything_up_to_the_last_flush(launch, ros_node, tmp_path):
    proc, pub, bag, cls = _start(launch, ros_node, tmp_path, 0.3)
    _publish(ros_node, pub, cls, range(30))
    ros_node.spin_for(1.5)  # several flush periods: the first 30 are on disk
    _publish(ros_node, pub, cls, range(30, 35))
    proc.send_signal(signal.SIGKILL)
    proc.wait(10)
    assert proc.returncode == -signal.SIGKILL
    assert (bag / "metadata.yaml").exists()  # written early, for every reader
    rec = read_bag(bag)  # no repair needed
    seqs = [f["seq"] for _, _, f in rec.topics["odometer"]]
    assert seqs[:30] == list(range(30)), seqs
    assert seqs == list(range(len(seqs)))  # nothing out of order or invented
    assert "not closed" in rec.skipped["(file tail)"]
    from rosbags.highlevel import AnyReader

    with AnyReader([bag]) as r:  # rosbags opens it as it is
        got = [r.deserialize(raw, c.msgtype).seq for c, _, raw in r.messages()]
    assert got == seqs


def test_one_topic_given_twice_is_refused_before_a_bag_is_made(launch, tmp_path):
    """``odometer`` and ``/rec/odometer`` are one topic: recorded twice, every message was
    written twice (949 in the bag for 475 published)."""
    bag = tmp_path / "bag"
    proc = launch.node("train_estimation", "recorder", "--ros-args", "-r", f"__ns:={NS}",
                       "-p", f"bag:={bag}", "-p", f"topics:=[odometer,{NS}/odometer]")
    proc.wait(timeout=60)
    out = open(proc.log_path).read()
    assert proc.returncode == 2, out
    assert [ln for ln in out.splitlines() if ln.strip()] == [
        "error: parameter topics: 'odometer' and '/rec/odometer' are one topic, "
        "/rec/odometer: give it once"], out
    assert not bag.exists()


@pytest.mark.parametrize("given,named", [({"flush_period": 0.0}, "flush_period"),
                                         ({"topics": ("odometer", "odometer")}, "topics"),
                                         ({"topics": ()}, "topics")])
def test_the_recorders_config_names_what_it_refuses(given, named):
    from train_core.config import ConfigError

    from train_estimation.nodes.recorder import RecorderConfig

    with pytest.raises(ConfigError, match=f"parameter {named}:"):
        RecorderConfig(bag="b", **given)


def test_a_stop_takes_what_the_subscriptions_hold_and_no_more_than_its_budget():
    """At a stop, the messages delivered to the recorder but not yet taken are taken (the run
    loop drains until the count of messages taken stays), and a publisher that goes on
    cannot hold the stop past the budget."""
    from train_core.ros import _drain

    class Node:
        taken = 0

    class Executor:
        def __init__(self, queued, endless=False):
            self.queued, self.endless = queued, endless

        def spin_once(self, timeout_sec):
            if self.queued or self.endless:
                self.queued = max(self.queued - 1, 0)
                node.taken += 1

    node = Node()
    _drain(Executor(500), node)
    assert node.taken == 500
    node.taken = 0
    import time

    t0 = time.monotonic()
    _drain(Executor(0, endless=True), node, budget=0.2)
    assert 0.2 <= time.monotonic() - t0 < 5.0 and node.taken > 0
