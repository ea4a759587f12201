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
