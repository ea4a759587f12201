"""Every docs/interfaces.md message crosses a process boundary with every field preserved."""

import json
import math
import random
import string
import sys
import time
import zlib
from pathlib import Path

import pytest
from train_core.ros import TYPES, msg_class, msg_to_dict

TOOL = str(Path(__file__).parent / "helpers" / "topic_tool.py")


def _random_value(kind: str, rng: random.Random):
    if kind == "float64":
        return rng.choice([rng.uniform(-1e6, 1e6), rng.gauss(0, 1e-9), -0.0, math.inf, -math.inf,
                           math.nan, 5e-324, 1.7976931348623157e308])
    if kind == "uint32":
        return rng.choice([0, 1, 2**32 - 1, rng.randrange(2**32)])
    if kind == "uint8":
        return rng.choice([0, 1, 2, 255, rng.randrange(256)])
    if kind == "int32":
        return rng.choice([-(2**31), 2**31 - 1, rng.randrange(-(2**31), 2**31)])
    if kind == "boolean":
        return rng.random() < 0.5
    if kind == "string":
        return "".join(rng.choice(string.ascii_letters + "_/ äé") for _ in range(rng.randrange(12)))
    raise AssertionError(kind)


def _random_fields(cls, rng: random.Random) -> dict:
    out = {}
    for name, kind in cls.get_fields_and_field_types().items():
        if kind == "std_msgs/Header":
            out[name] = {"stamp": {"sec": rng.randrange(2**31), "nanosec": rng.randrange(10**9)},
                         "frame_id": _random_value("string", rng)}
        elif kind.startswith("double["):
            n = int(kind[len("double["):-1])
            out[name] = [_random_value("float64", rng) for _ in range(n)]
        else:
            out[name] = _random_value({"double": "float64", "uint32": "uint32", "uint8": "uint8",
                                       "boolean": "boolean", "string": "string"}[kind], rng)
    return out


def _same(a, b) -> bool:
    if isinstance(a, dict):
        return a.keys() == b.keys() and all(_same(a[k], b[k]) for k in a)
    if isinstance(a, list):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b))
    if isinstance(a, float):
        if math.isnan(a):
            return isinstance(b, float) and math.isnan(b)
        return a == b and math.copysign(1, a) == math.copysign(1, b)
    return a == b and type(a) is type(b)


@pytest.mark.parametrize("type_name", sorted(TYPES))
def test_message_roundtrip_between_processes(type_name, launch, tmp_path):
    rng = random.Random(zlib.crc32(type_name.encode()))
    cls = msg_class(type_name)
    sent = [_random_fields(cls, rng) for _ in range(20)]
    # the dicts are valid messages: converting through the class keeps them as they are
    src = tmp_path / "in.json"
    src.write_text(json.dumps(sent))
    out = tmp_path / "out.jsonl"
    topic = f"roundtrip_{type_name.lower()}"
    launch.start([sys.executable, TOOL, "echo", type_name, topic, str(out)], name="echo")
    launch.start([sys.executable, TOOL, "pub", type_name, topic, str(src)], name="pub")
    deadline = time.monotonic() + 30
    got: list = []
    while time.monotonic() < deadline:
        if out.exists():
            got = [json.loads(line) for line in out.read_text().splitlines() if line]
            if len(got) >= len(sent):
                break
        time.sleep(0.1)
    assert len(got) == len(sent), f"received {len(got)} of {len(sent)}\n{launch.logs()}"
    for s, g in zip(sent, got):
        assert _same(s, g), f"sent {s}\n got {g}"
    # and the in-process conversion is the identity on these messages
    from train_core.ros import dict_to_msg

    for s in sent:
        assert _same(s, msg_to_dict(dict_to_msg(s, cls())))
