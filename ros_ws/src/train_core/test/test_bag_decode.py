"""bagio.deserialize reads fixed-layout messages with one struct unpack: exactly what rosbags'
decoder gives (stamp, every field, its Python type), for every frame_id length (CDR aligns the
fields after the string), and the general decoder for anything else."""

import math

import numpy as np
import pytest
from train_core import bagio


def _general(msgtype, raw):
    msg = bagio.own_typestore().deserialize_cdr(raw, msgtype)
    fields = {k: getattr(msg, k) for k in msg.__dataclass_fields__
              if k not in ("header", "__msgtype__")}
    return msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9, fields


FIELDS = {
    "train_interfaces/msg/OdometerReading": ("seq", "distance", "speed", "speed_variance"),
    "train_interfaces/msg/BaliseReading": ("seq", "balise_id", "position",
                                           "position_variance"),
    "train_interfaces/msg/ControlCommand": ("target_acceleration",),
}


@pytest.mark.parametrize("msgtype", sorted(FIELDS))
@pytest.mark.parametrize("frame_id", ["", "t", "tr", "track", "trac", "a_longer_frame"])
def test_fixed_layouts_decode_as_rosbags_does(msgtype, frame_id):
    rng = np.random.default_rng(len(frame_id))
    for _ in range(20):
        fields = {k: (int(rng.integers(0, 2**32)) if k in ("seq", "balise_id")
                      else float(rng.normal() * 10.0 ** rng.integers(-300, 300)))
                  for k in FIELDS[msgtype]}
        stamp = float(rng.uniform(-1e6, 2e9))
        raw = bagio.serialize(msgtype, fields, stamp, frame_id=frame_id)
        fast = bagio._deserialize_fixed(msgtype, raw)
        assert fast is not None
        want = _general(msgtype, raw)
        assert fast[0] == want[0] and list(fast[1]) == list(want[1])
        for k, v in want[1].items():
            assert type(fast[1][k]) is type(v) and fast[1][k] == v
        assert bagio.deserialize(msgtype, raw) == fast
        assert list(fast[1]) == list(FIELDS[msgtype])
        assert all(fast[1][k] == fields[k] for k in fields)


def test_other_messages_use_the_general_decoder():
    fields = {"source": "gsma", "position": 1.0, "velocity": 2.0, "acceleration": 0.1,
              "braking_rate": math.nan, "covariance": np.arange(16.0),
              "measurement_used": True, "integrity": 1, "protection_level_ahead": 3.0,
              "protection_level_behind": 4.0}
    mt = "train_interfaces/msg/TrainState"
    raw = bagio.serialize(mt, fields, 12.5)
    assert bagio._fixed_fields(mt) is None and bagio._deserialize_fixed(mt, raw) is None
    stamp, got = bagio.deserialize(mt, raw)
    assert stamp == 12.5 and got["source"] == "gsma"
    assert np.array_equal(got["covariance"], np.arange(16.0))


def test_bytes_that_do_not_fit_the_layout_fall_back():
    mt = "train_interfaces/msg/OdometerReading"
    raw = bagio.serialize(mt, {"seq": 1, "distance": 2.0, "speed": 3.0,
                               "speed_variance": 0.01}, 1.0)
    assert bagio._deserialize_fixed(mt, b"\x01\x00" + raw[2:]) is None  # big-endian CDR
    assert bagio._deserialize_fixed(mt, raw + bytes(8)) is None  # a longer (other) definition
    assert bagio._deserialize_fixed(mt, raw[:-8]) is None  # cut short
