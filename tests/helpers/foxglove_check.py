"""docs/foxglove_layout.json against a real recorded bag (the main job's).

Every panel's topic is in the bag and every plotted field resolves on its messages; the layout's
user script (docs/foxglove_train_errors.ts, run with node) fed the bag's messages in receive
order, as Foxglove plays them, gives for each estimator the plots select the error estimate -
truth at the same sample stamp; the diagnostics panel's topic carries every node's status.
"""

from __future__ import annotations

import json
import math
import re
import shutil
import subprocess
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[2]
LAYOUT = REPO / "docs" / "foxglove_layout.json"
SCRIPT = REPO / "docs" / "foxglove_train_errors.ts"
PATH_RE = re.compile(r'(/[\w/]+?)(\{source=="(\w+)"\})?\.([\w.]+)')


def bag_messages(bag: Path) -> dict[str, list[tuple[int, object]]]:
    """Every message of the bag, decoded (train_interfaces and common_interfaces types):
    topic -> [(log time ns, message)] in log-time order."""
    from rosbags.highlevel import AnyReader
    from train_core.bagio import typestore

    out: dict[str, list] = {}
    with AnyReader([bag], default_typestore=typestore()) as reader:
        for conn, t_ns, raw in reader.messages():
            out.setdefault(conn.topic, []).append((t_ns, reader.deserialize(raw, conn.msgtype)))
    return out


def to_plain(msg):
    """A rosbags message as JSON-able plain data (Foxglove's view of it: Time has sec/nsec)."""
    if isinstance(msg, np.ndarray):
        return [to_plain(v) for v in msg.tolist()]
    if isinstance(msg, (list, tuple)):
        return [to_plain(v) for v in msg]
    if hasattr(msg, "__dataclass_fields__"):
        d = {k: to_plain(getattr(msg, k)) for k in msg.__dataclass_fields__
             if k != "__msgtype__"}
        if set(d) == {"sec", "nanosec"}:
            d = {"sec": d["sec"], "nsec": d["nanosec"]}
        return d
    if isinstance(msg, float) and not math.isfinite(msg):
        return None  # JSON; the script reads NaN covariances through Math.max(.., 0)
    return msg


def field(msg, dotted: str):
    for part in dotted.split("."):
        msg = getattr(msg, part)
    return msg


def _stamp_ms(stamp) -> int:
    return round(stamp.sec * 1e3 + stamp.nanosec / 1e6)


def check_layout(bag: Path, workdir: Path, nodes: set[str]) -> dict:
    """Assert the layout works on ``bag``; returns {source: number of script outputs}."""
    layout = json.loads(LAYOUT.read_text())
    messages = bag_messages(bag)
    ts = SCRIPT.read_text()
    (script,) = layout["userNodes"].values()
    assert script["sourceCode"] == ts  # the layout carries the reviewed script
    out_topic = re.search(r'export const output = "([^"]+)"', ts).group(1)
    inputs = json.loads(re.sub(r",\s*\]", "]", re.search(
        r"export const inputs = (\[[^\]]*\])", ts).group(1)))
    for topic in inputs:
        assert messages.get(topic), f"script input {topic} is not in the bag"

    # the user script, run by node on the bag's messages in receive (log time) order
    node = shutil.which("node")
    assert node, "node is needed to run the layout's user script"
    events = sorted(((t, topic, m) for topic in inputs for t, m in messages[topic]),
                    key=lambda e: e[0])
    (workdir / "script.mjs").write_text(strip_types(ts))
    (workdir / "events.json").write_text(json.dumps(
        [{"topic": topic, "message": to_plain(m)} for _, topic, m in events]))
    (workdir / "run.mjs").write_text(
        'import fs from "fs";\nconst mod = await import("./script.mjs");\n'
        'const evs = JSON.parse(fs.readFileSync("events.json"));\n'
        "const out = evs.map((e) => mod.default(e)).filter((o) => o !== undefined);\n"
        "console.log(JSON.stringify(out));\n")
    run = subprocess.run([node, "run.mjs"], cwd=workdir, capture_output=True, text=True,
                         timeout=120)
    assert run.returncode == 0, run.stderr
    outputs = json.loads(run.stdout)
    # what it must compute: each estimate - the truth of its sample stamp (received earlier)
    truth: dict[int, object] = {}
    expected = []
    for _, topic, m in events:
        key = _stamp_ms(m.header.stamp)
        if topic.endswith("/ground_truth"):
            truth[key] = m
        elif key in truth:
            t = truth[key]
            expected.append((m.source, m.position - t.position, m.velocity - t.velocity,
                             3 * math.sqrt(max(m.covariance[0], 0.0))))
    assert len(outputs) == len(expected) > 0
    for o, (source, dx, dv, s3) in zip(outputs, expected):
        assert o["source"] == source
        assert math.isclose(o["position_error"], dx, rel_tol=1e-12, abs_tol=1e-12)
        assert math.isclose(o["velocity_error"], dv, rel_tol=1e-12, abs_tol=1e-12)
        assert math.isclose(o["position_3sigma"], s3, rel_tol=1e-12, abs_tol=1e-12)
    by_source: dict[str, list[dict]] = {}
    for o in outputs:
        by_source.setdefault(o["source"], []).append(o)

    for panel, cfg in layout["configById"].items():
        kind = panel.split("!")[0]
        if kind == "DiagnosticSummary":
            topic = cfg["topicToRender"]
            assert messages.get(topic), f"{panel}: {topic} is not in the bag"
            names = {s.name.split(":")[0] for _, a in messages[topic] for s in a.status}
            assert nodes <= names, (panel, nodes - names)
            levels = {int(s.level[0]) if isinstance(s.level, (bytes, bytearray)) else
                      int(s.level) for _, a in messages[topic] for s in a.status}
            assert levels <= {0, 1, 2}, levels
            continue
        assert kind == "Plot", panel
        for p in cfg["paths"]:
            m = PATH_RE.fullmatch(p["value"])
            assert m, p["value"]
            topic, _, source, path = m.groups()
            if topic == out_topic:
                rows = by_source.get(source, [])
                assert rows, f"{panel}: the script gives nothing for source {source!r}"
                assert all(isinstance(r[path], (int, float)) for r in rows), (panel, path)
                continue
            msgs = messages.get(topic)
            assert msgs, f"{panel}: {topic} is not in the bag"
            if source is not None:
                msgs = [(t, x) for t, x in msgs if x.source == source]
                assert msgs, f"{panel}: no message with source {source!r} on {topic}"
            vals = [field(x, path) for _, x in msgs]
            assert all(isinstance(v, (bool, int, float, np.generic)) for v in vals), (panel, p)
            assert any(math.isfinite(float(v)) for v in vals), (panel, p)
    return {s: len(v) for s, v in by_source.items()}


def strip_types(ts: str) -> str:
    """JavaScript of the TypeScript user script (its type-only parts removed), so node runs it;
    fails loudly if the script grows constructs this does not know."""
    js = re.sub(r"^type \w+ = \{.*?^\};\n", "", ts, flags=re.S | re.M)
    js = re.sub(r"^type \w+ = [^\n]*\n", "", js, flags=re.M)
    js = re.sub(r"new Map<[^\n]*>\(\)", "new Map()", js)
    js = re.sub(r"function stampMs\([^\n]*\): number", "function stampMs(stamp)", js)
    js = re.sub(r"export default function script\([^\n]*\): Output \| undefined",
                "export default function script(event)", js)
    js = js.replace("const cov: number[] =", "const cov =")
    assert not re.search(r"\b(type|interface)\s+\w+\s*=|: (number|string|any)\b", js), js
    return js
