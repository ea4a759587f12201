"""bagio.deserialize reads fixed-layout messages with one struct unpack: exactly what rosbags'
decoder gives (stamp, every field, its Python type), for every frame_id length (CDR aligns the
fields after the string), and the general decoder for anything else. bagio.serialize writes them
with one struct pack: the bytes rosbags' serialiser gives."""

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


def _rosbags_bytes(msgtype, fields, stamp, frame_id="track"):
    ts = bagio.typestore()
    return bytes(ts.serialize_cdr(bagio._build(ts, msgtype, fields, stamp, frame_id), msgtype))


@pytest.mark.parametrize("msgtype", sorted(FIELDS))
@pytest.mark.parametrize("frame_id", ["", "t", "tr", "track", "trac", "a_longer_frame"])
def test_fixed_layouts_encode_as_rosbags_does(msgtype, frame_id):
    """Byte for byte, over magnitudes from 1e-300 to 1e300, the non-finite values, numpy
    scalars and negative stamps; fields that do not fit the layout (a negative or a fractional
    count, one missing) go the general way, which says what is wrong."""
    rng = np.random.default_rng(7 + len(frame_id))
    specials = [math.nan, math.inf, -math.inf, -0.0, 5e-324]
    for k in range(40):
        fields = {n: (int(rng.integers(0, 2**32)) if n in ("seq", "balise_id")
                      else float(rng.normal() * 10.0 ** rng.integers(-300, 300))
                      if k >= len(specials) else specials[k])
                  for n in FIELDS[msgtype]}
        if k % 4 == 1:
            fields = {n: np.int64(v) if isinstance(v, int) else np.float64(v)
                      for n, v in fields.items()}
        stamp = float(rng.uniform(-1e6, 2e9))
        fast = bagio._serialize_fixed(msgtype, fields, stamp, frame_id)
        assert fast is not None and fast == _rosbags_bytes(msgtype, fields, stamp, frame_id)
        assert bagio.serialize(msgtype, fields, stamp, frame_id=frame_id) == fast
    bad = dict.fromkeys(FIELDS[msgtype], 1.0)
    del bad[FIELDS[msgtype][0]]
    wrong = [bad]
    if "seq" in FIELDS[msgtype]:
        wrong += [{**dict.fromkeys(FIELDS[msgtype], 1.0), "seq": -1, "balise_id": 1},
                  {**dict.fromkeys(FIELDS[msgtype], 1.0), "seq": 1.5, "balise_id": 1}]
    for fields in wrong:
        assert bagio._serialize_fixed(msgtype, fields, 1.0, frame_id) is None
        with pytest.raises(Exception) as fast:
            bagio.serialize(msgtype, fields, 1.0, frame_id=frame_id)
        with pytest.raises(Exception) as general:
            _rosbags_bytes(msgtype, fields, 1.0, frame_id)
        assert type(fast.value) is type(general.value)


def test_our_other_messages_encode_as_with_the_standard_types():
    """TrainState goes the general way, on our own types only: the same bytes as with ROS 2's
    standard message set, which a writer then need not build."""
    rng = np.random.default_rng(3)
    mt = "train_interfaces/msg/TrainState"
    for k in range(20):
        fields = {"source": "kf" * k, "position": float(rng.normal() * 1e4),
                  "velocity": float(rng.random()), "acceleration": float(rng.normal()),
                  "braking_rate": math.nan if k % 3 else 0.5, "covariance": rng.normal(size=16),
                  "measurement_used": bool(k % 2), "integrity": k % 3,
                  "protection_level_ahead": math.inf if k % 4 else 2.0,
                  "protection_level_behind": float(rng.random())}
        assert bagio.serialize(mt, fields, k * 0.7) == _rosbags_bytes(mt, fields, k * 0.7)


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


def _rosbags_read(path, topics):
    orig = bagio._read_plain
    bagio._read_plain = lambda *a: None
    try:
        return bagio.read_bag(path, topics=topics)
    finally:
        bagio._read_plain = orig


def _same(a, b):
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        return type(a) is type(b) and np.array_equal(a, b, equal_nan=True)
    if isinstance(a, float) and math.isnan(a):
        return isinstance(b, float) and math.isnan(b)
    return type(a) is type(b) and a == b


def test_plain_mcap_bags_are_read_as_rosbags_reads_them(tmp_path):
    """read_bag walks a closed one-file bag with plain chunks itself: the same Bag as through
    rosbags' reader (topics, types, skipped topics, each topic in log-time order with ties in
    file order), over several chunks, messages written out of time order and a topic of
    another type."""
    rng = np.random.default_rng(5)
    path = tmp_path / "bag"
    state = {"source": "gsma", "position": 1.0, "velocity": 2.0, "acceleration": 0.1,
             "braking_rate": math.nan, "covariance": np.arange(16.0),
             "measurement_used": True, "integrity": 0, "protection_level_ahead": 3.0,
             "protection_level_behind": 4.0}
    with bagio.BagWriter(path) as w:
        for k in range(300):
            t = float(rng.uniform(0, 60))
            t_ns = int(t * 1e9) if k % 7 else 5_000_000_000  # ties in log time
            w.write("odometer", t, {"seq": k, "distance": float(rng.normal()), "speed": t,
                                    "speed_variance": 0.01}, t_ns=t_ns)
            if k % 10 == 0:
                w.write("control", t, {"target_acceleration": float(rng.normal())}, t_ns=t_ns)
                w.write("estimate/gsma", t, state)
                w.write_raw("/train/clock_other", "rosgraph_msgs/msg/Clock", t_ns,
                            bagio.typestore().serialize_cdr(
                                bagio.typestore().types["rosgraph_msgs/msg/Clock"](
                                    clock=bagio.typestore().types[
                                        "builtin_interfaces/msg/Time"](sec=1, nanosec=2)),
                                "rosgraph_msgs/msg/Clock").tobytes())
            if k % 50 == 0:
                w.write_raw("/train/diag", "std_msgs/msg/String", t_ns,
                            bagio.typestore().serialize_cdr(
                                bagio.typestore().types["std_msgs/msg/String"](data="x"),
                                "std_msgs/msg/String").tobytes())
                w.flush()  # a new chunk
    for topics in (None, ("odometer", "control")):
        got = bagio._read_plain(path, None, topics)
        assert got is not None
        want = _rosbags_read(path, topics)
        assert got.namespace == want.namespace and list(got.topics) == list(want.topics)
        assert list(got.types.items()) == list(want.types.items())
        assert list(got.skipped.items()) == list(want.skipped.items())
        assert "/train/diag" in got.skipped
        for k, msgs in want.topics.items():
            assert len(got.topics[k]) == len(msgs) > 0
            for (t1, s1, f1), (t2, s2, f2) in zip(got.topics[k], msgs):
                assert t1 == t2 and s1 == s2 and list(f1) == list(f2)
                assert all(_same(f1[x], f2[x]) for x in f1)
        assert bagio.read_bag(path, topics=topics).topics.keys() == want.topics.keys()


def test_other_bags_are_left_to_rosbags(tmp_path):
    """Two MCAP files, or a compressed chunk: not read here (rosbags reads them)."""
    path = tmp_path / "bag"
    with bagio.BagWriter(path) as w:
        w.write("control", 1.0, {"target_acceleration": 0.5})
    assert bagio._read_plain(path, None, None) is not None
    mcap = next(path.glob("*.mcap"))
    (path / "second.mcap").write_bytes(mcap.read_bytes())
    assert bagio._read_plain(path, None, None) is None
    (path / "second.mcap").unlink()
    data = mcap.read_bytes()
    at = 8  # walk the records to the first chunk, then name a compression in it
    while data[at] != 0x06:
        at += 9 + int.from_bytes(data[at + 1:at + 9], "little")
    n = int.from_bytes(data[at + 1:at + 9], "little")
    assert bagio._read_plain(mcap, None, None) is not None
    mcap.write_bytes(data[:at + 1] + (n + 4).to_bytes(8, "little") + data[at + 9:at + 37]
                     + (4).to_bytes(4, "little") + b"zstd" + data[at + 41:])
    assert bagio._read_plain(mcap, None, None) is None
