"""An estimate's two messages (TrainState and nav_msgs/Odometry) written straight as the bytes
rclpy would serialise, from per-node templates.

Filled as Python messages, rclpy converts both to C structs and serialises them in
``publish``: 34 us per estimate at the median and 75 us at the p99 with both published;
``struct.pack_into`` on a template of each, published as bytes (``publish_raw``), costs 12 and
26 us (``./run bench publish``, docs/benchmarks.md). The messages are the same: a template is
the node's own message (:func:`node_messages`) serialised once by rclpy, and only the fields
an estimate sets are written, at offsets found by serialising marker values (CDR puts
fixed-size fields at fixed offsets, and these two messages hold no string or
sequence an estimate changes). ``tests/test_estimate_cdr.py`` checks every field against
rclpy's serialisation for estimates of every kind (NaN, infinite levels, negative and large
stamps); the alignment padding is whatever each serialiser's buffer held.

A stamp whose seconds do not fit the message's int32 (beyond 2038 at the Unix epoch) is not
written here (:meth:`EstimateCdr.encode` returns None): the node then fills the messages, and
what rclpy makes of such a stamp is published as before.
"""

from __future__ import annotations

import struct

from nav_msgs.msg import Odometry
from rclpy.serialization import serialize_message

from train_estimation.core.online.odometry import odometry_covariances
from train_interfaces.msg import TrainState

_SEC, _NSEC = 0x5A5A5A5A, 0x3C3C3C3C  # marker stamp (each packed value occurs once)
_STATE_FLOATS = ("position", "velocity", "acceleration", "braking_rate",
                 "protection_level_ahead", "protection_level_behind")


def _at(blob: bytes, value: bytes) -> int:
    """The one offset of ``value`` in ``blob`` (a marker that occurs twice is a bad marker)."""
    i = blob.find(value)
    if i < 0 or blob.find(value, i + 1) >= 0:
        raise ValueError(f"marker {value.hex()} found {blob.count(value)} times")
    return i


def node_messages(source: str) -> tuple[TrainState, Odometry]:
    """An estimator node's TrainState and Odometry with the fields no estimate changes set:
    the frames (docs/ros.md), the TrainState's ``source``, the Odometry's orientation (the
    body x axis along the track's)."""
    state = TrainState()
    state.header.frame_id, state.source = "track", source
    odom = Odometry()
    odom.header.frame_id, odom.child_frame_id = "track", "base_link"
    odom.pose.pose.orientation.w = 1.0
    return state, odom


class EstimateCdr:
    """The CDR bytes of one node's TrainState and Odometry per estimate (``source``: the
    TrainState's; the rest as :func:`node_messages` sets it)."""

    def __init__(self, source: str):
        s, o = node_messages(source)
        s.header.stamp.sec, s.header.stamp.nanosec = _SEC, _NSEC
        marks = {k: 1000.0 + 0.123456789 * (i + 1) for i, k in enumerate(_STATE_FLOATS)}
        for k, v in marks.items():
            setattr(s, k, v)
        s.covariance = [2000.0 + 0.987654321 * i for i in range(16)]
        s.measurement_used, s.integrity = False, 0
        blob = serialize_message(s)
        self.s_sec = _at(blob, struct.pack("<i", _SEC))
        self.s_nsec = _at(blob, struct.pack("<I", _NSEC))
        self.s_float = [_at(blob, struct.pack("<d", marks[k])) for k in _STATE_FLOATS]
        self.s_cov = _at(blob, struct.pack("<d", 2000.0))
        # the bool and the uint8: the two bytes that change when they are set
        s.measurement_used, s.integrity = True, 0xA7
        other = serialize_message(s)
        diff = [i for i, (a, b) in enumerate(zip(blob, other)) if a != b]
        if len(diff) != 2 or len(blob) != len(other):
            raise ValueError(f"TrainState's bool and uint8 not found: bytes {diff} differ")
        self.s_used, self.s_integrity = diff
        self.state = bytearray(blob)

        o.header.stamp.sec, o.header.stamp.nanosec = _SEC, _NSEC
        o.pose.pose.position.x = 3000.123456789
        o.twist.twist.linear.x = 4000.123456789
        o.pose.covariance = [5000.0 + 0.5 * i for i in range(36)]
        o.twist.covariance = [6000.0 + 0.5 * i for i in range(36)]
        blob = serialize_message(o)
        self.o_sec = _at(blob, struct.pack("<i", _SEC))
        self.o_nsec = _at(blob, struct.pack("<I", _NSEC))
        self.o_x = _at(blob, struct.pack("<d", 3000.123456789))
        self.o_v = _at(blob, struct.pack("<d", 4000.123456789))
        self.o_pose = _at(blob, struct.pack("<d", 5000.0))
        self.o_twist = _at(blob, struct.pack("<d", 6000.0))
        self.odom = bytearray(blob)

    def encode(self, out, risk: float) -> tuple[bytes, bytes] | None:
        """(TrainState bytes, Odometry bytes) of a runner ``Output``: what ``fill_state`` and
        ``fill_odometry`` then rclpy's serialisation make of it (``risk``: the integrity risk
        the levels are stated at); None for a stamp beyond int32 seconds (module doc)."""
        ns = int(round(out.stamp * 1e9))  # as train_core.ros.sec_to_stamp
        sec, nsec = divmod(ns, 1_000_000_000)
        if not -2 ** 31 <= sec < 2 ** 31:
            return None
        pack = struct.pack_into
        b = self.state
        pack("<i", b, self.s_sec, sec)
        pack("<I", b, self.s_nsec, nsec)
        f = self.s_float
        pack("<d", b, f[0], out.position)
        pack("<d", b, f[1], out.velocity)
        pack("<d", b, f[2], out.acceleration)
        pack("<d", b, f[3], out.braking_rate)
        pack("<d", b, f[4], out.protection_level_ahead)
        pack("<d", b, f[5], out.protection_level_behind)
        pack("<16d", b, self.s_cov, *out.covariance)
        b[self.s_used] = 1 if out.measurement_used else 0
        b[self.s_integrity] = out.integrity
        pose, twist = odometry_covariances(
            out.covariance, (out.protection_level_ahead, out.protection_level_behind, risk))
        o = self.odom
        pack("<i", o, self.o_sec, sec)
        pack("<I", o, self.o_nsec, nsec)
        pack("<d", o, self.o_x, out.position)
        pack("<d", o, self.o_v, out.velocity)
        pack("<36d", o, self.o_pose, *pose)
        pack("<36d", o, self.o_twist, *twist)
        return bytes(b), bytes(o)
