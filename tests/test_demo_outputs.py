"""What a new user opens besides the report: the Foxglove layout and the README's commands."""

import json
import re
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
MSG = REPO / "ros_ws" / "src" / "train_interfaces" / "msg"
TOPIC_MSG = {"ground_truth": "TrainState", "estimate/robust": "TrainState",
             "estimate/gsma": "TrainState", "control": "ControlCommand",
             "movement_authority": "MovementAuthority"}


def _fields(msg: str) -> set[str]:
    return {line.split()[1] for line in (MSG / f"{msg}.msg").read_text().splitlines()
            if line.strip() and not line.startswith("#")}


def test_foxglove_layout_plots_fields_that_exist():
    layout = json.loads((REPO / "docs" / "foxglove_layout.json").read_text())
    (script,) = layout["userNodes"].values()
    src = (REPO / "docs" / "foxglove_train_errors.ts").read_text()
    assert script["sourceCode"] == src  # the layout carries the reviewed script
    out_topic = re.search(r'export const output = "([^"]+)"', src).group(1)
    block = src.split("type Output = {")[1].split("\n};")[0]
    out_fields = set(re.findall(r"^  (\w+): ", block, re.M))
    inputs = json.loads(re.search(r"export const inputs = (\[[^\]]*\])", src).group(1))
    assert inputs == ["/train/ground_truth", "/train/estimate/robust", "/train/estimate/gsma"]
    for name in re.findall(r"\bm\.(\w+)", src):  # what the script reads from TrainState
        assert name in _fields("TrainState"), name
    plotted = []
    for panel, cfg in layout["configById"].items():
        assert panel.startswith("Plot!") and cfg["title"]
        for path in cfg["paths"]:
            m = re.fullmatch(r'(/[\w/]+?)(\{source=="(\w+)"\})?\.(\w+)', path["value"])
            assert m, path["value"]
            topic, _, source, field = m.groups()
            if topic == out_topic:
                assert field in out_fields and source in ("robust_filter", "gsma"), path
            else:
                assert topic.startswith("/train/"), topic
                assert field in _fields(TOPIC_MSG[topic[len("/train/"):]]), path
            plotted.append((topic, field))
    for want in [(out_topic, "position_error"), (out_topic, "velocity_error"),
                 ("/train/estimate/gsma", "braking_rate"), ("/train/ground_truth", "braking_rate")]:
        assert want in plotted
    ids = set(layout["configById"])

    def leaves(node):
        return {node} if isinstance(node, str) else leaves(node["first"]) | leaves(node["second"])

    assert leaves(layout["layout"]) == ids


def test_readme_commands_use_files_that_exist():
    readme = (REPO / "README.md").read_text()
    # repository paths only (not outputs such as out/docs/...)
    paths = set(re.findall(r"(?<![\w/])(?:ros_ws|docs)/[\w./-]+\.(?:yaml|json|png|ts|csv)",
                           readme))
    assert paths
    missing = [p for p in sorted(paths) if not (REPO / p).exists()]
    assert not missing, missing
    assert "L.yaml" not in readme and "T.yaml" not in readme  # no placeholders


def _strip_types(ts: str) -> str:
    """JavaScript of docs/foxglove_train_errors.ts (its TypeScript-only parts removed), so node
    can run it; fails loudly if the script grows constructs this does not know."""
    js = re.sub(r"^type \w+ = \{.*?^\};\n", "", ts, flags=re.S | re.M)
    js = re.sub(r"^type \w+ = [^\n]*\n", "", js, flags=re.M)
    js = re.sub(r"new Map<[^\n]*>\(\)", "new Map()", js)
    js = re.sub(r"function stampMs\([^\n]*\): number", "function stampMs(stamp)", js)
    js = re.sub(r"export default function script\([^\n]*\): Output \| undefined",
                "export default function script(event)", js)
    js = js.replace("const cov: number[] =", "const cov =")
    assert not re.search(r"\b(type|interface)\s+\w+\s*=|: (number|string|any)\b", js), js
    return js


def test_foxglove_script_computes_the_errors_check_bag_computes(tmp_path):
    """Run the layout's user script (node) on a generated run with a fake estimator: its errors
    and 3-sigma are estimate - truth at the same sample stamp, for every estimate."""
    import math
    import shutil
    import subprocess

    import numpy as np
    import pytest

    from train_sim.generate import generate
    from train_sim.scenario import load_scenario

    node = shutil.which("node")
    if node is None:
        pytest.skip("node is not installed")
    res = generate(load_scenario("metro_demo"), tmp_path / "bag", seed=2, duration=20.0)
    rng = np.random.default_rng(0)
    events, expected = [], []
    for topic, stamp, f in res.events():
        if topic != "ground_truth":
            continue
        sec, nsec = int(stamp), int(round((stamp - int(stamp)) * 1e9))
        head = {"stamp": {"sec": sec, "nsec": nsec}}
        events.append({"topic": "/train/ground_truth", "message": {
            "header": head, "position": f["position"], "velocity": f["velocity"],
            "braking_rate": f["braking_rate"], "covariance": [None] * 16}})
        dx, dv, sx = rng.normal(0, 0.3), rng.normal(0, 0.05), rng.uniform(0.1, 1.0)
        cov = [0.0] * 16
        cov[0], cov[5] = sx**2, 0.01
        events.append({"topic": "/train/estimate/gsma", "message": {
            "header": head, "source": "gsma", "position": f["position"] + dx,
            "velocity": f["velocity"] + dv, "braking_rate": 0.9, "covariance": cov}})
        expected.append((dx, dv, 3 * sx))
    (tmp_path / "script.mjs").write_text(
        _strip_types((REPO / "docs" / "foxglove_train_errors.ts").read_text()))
    (tmp_path / "events.json").write_text(json.dumps(events))
    (tmp_path / "run.mjs").write_text(
        'import fs from "fs";\nconst mod = await import("./script.mjs");\n'
        'const evs = JSON.parse(fs.readFileSync("events.json"));\n'
        "const out = evs.map((e) => mod.default(e)).filter((o) => o !== undefined);\n"
        "console.log(JSON.stringify(out));\n")
    run = subprocess.run([node, "run.mjs"], cwd=tmp_path, capture_output=True, text=True,
                         timeout=60)
    assert run.returncode == 0, run.stderr
    out = json.loads(run.stdout)
    assert len(out) == len(expected) == 201
    for o, (dx, dv, s3) in zip(out, expected):
        assert o["source"] == "gsma"
        assert math.isclose(o["position_error"], dx, abs_tol=1e-9)
        assert math.isclose(o["velocity_error"], dv, abs_tol=1e-9)
        assert math.isclose(o["position_3sigma"], s3, rel_tol=1e-12)
        assert math.isclose(o["velocity_3sigma"], 0.3, rel_tol=1e-12)
