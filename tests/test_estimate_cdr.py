"""The estimator nodes' messages written from templates are the messages rclpy serialises:
every field the same to the bit (NaN payloads included), in bytes of the same length. The CDR
alignment padding is not compared: rclpy's serialiser leaves whatever its buffer held there
(the two differ in those bytes), and no reader looks at them."""

import math

import numpy as np
import pytest
from nav_msgs.msg import Odometry
from rclpy.serialization import deserialize_message, serialize_message

from train_estimation.core.online.runner import Output
from train_estimation.nodes.estimate_cdr import EstimateCdr, node_messages
from train_estimation.nodes.estimator_node import fill_odometry, fill_state
from train_interfaces.msg import TrainState


def _outputs(rng: np.random.Generator, n: int):
    special = (math.nan, math.inf, -math.inf, 0.0, -0.0, 5e-324, 1e308)
    for i in range(n):
        def x(scale=1e3):
            return special[rng.integers(len(special))] if rng.random() < 0.1 \
                else float(rng.normal(0, scale))
        stamp = (x(1e9) if rng.random() < 0.5 else float(rng.uniform(-100, 2e9)))
        if not math.isfinite(stamp) or abs(stamp) > 2e9:
            stamp = float(rng.uniform(-2e9, 2e9))
        # levels: a length, or no bound (their square is an Odometry variance: no 1e308)
        ahead, behind = (math.inf if rng.random() < 0.2 else abs(float(rng.normal(0, 50)))
                         for _ in range(2))
        yield Output(stamp=stamp, position=x(), velocity=x(30), acceleration=x(1),
                     braking_rate=x(1), covariance=tuple(x(10) for _ in range(16)),
                     measurement_used=bool(i % 2), integrity=int(rng.integers(3)),
                     protection_level_ahead=ahead, protection_level_behind=behind)


def _fields(msg) -> tuple:
    """Every field of a message, recursively; floats as their bits."""
    out = []
    for name in msg.get_fields_and_field_types():
        v = getattr(msg, name)
        if hasattr(v, "get_fields_and_field_types"):
            out.append((name, _fields(v)))
        elif isinstance(v, (float, np.floating)):
            out.append((name, np.float64(v).tobytes()))
        elif isinstance(v, (np.ndarray, list, tuple)):
            out.append((name, np.asarray(v, dtype=np.float64).tobytes()))
        else:
            out.append((name, repr(v)))
    return tuple(out)


def _same(fast: bytes, ref: bytes, msg_type) -> bool:
    return len(fast) == len(ref) and \
        _fields(deserialize_message(fast, msg_type)) == _fields(deserialize_message(ref, msg_type))


@pytest.mark.parametrize("source", ["robust_filter", "gsma", "kf", "a_source_name_of_odd_len"])
def test_template_bytes_are_rclpys_bytes(source):
    state, odom = node_messages(source)  # the node's own, refilled as it refills them
    cdr = EstimateCdr(source)
    rng = np.random.default_rng(5)
    for risk in (1e-7, 0.5, math.nan):
        for out in _outputs(rng, 300):
            fast_state, fast_odom = cdr.encode(out, risk)
            fill_state(state, out)
            fill_odometry(odom, state, risk)
            assert _same(fast_state, serialize_message(state), TrainState), out
            assert _same(fast_odom, serialize_message(odom), Odometry), out


def test_a_stamp_beyond_int32_seconds_is_left_to_rclpy():
    """rclpy serialises such a stamp somehow; the node then fills the messages as before."""
    cdr = EstimateCdr("kf")
    for stamp in (2.0 ** 31, -2.0 ** 31 - 1.0, 3e9):
        out = Output(stamp=stamp, position=0.0, velocity=0.0, acceleration=0.0,
                     braking_rate=1.0, covariance=(0.0,) * 16, measurement_used=False)
        assert cdr.encode(out, 1e-7) is None
    out = Output(stamp=2.0 ** 31 - 1.0, position=0.0, velocity=0.0, acceleration=0.0,
                 braking_rate=1.0, covariance=(0.0,) * 16, measurement_used=False)
    assert cdr.encode(out, 1e-7) is not None
