"""What a new user opens besides the report: the Foxglove layout and the README's commands."""

import json
import re
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
MSG = REPO / "ros_ws" / "src" / "train_interfaces" / "msg"
TOPIC_MSG = {"ground_truth": "TrainState", "estimate/robust": "TrainState",
             "estimate/gsma": "TrainState", "estimate/kf": "TrainState",
             "control": "ControlCommand", "movement_authority": "MovementAuthority"}
SOURCES = ("robust_filter", "gsma", "kf")  # the main job's three estimators
ODOM_FIELDS = ("pose.pose.position.x", "twist.twist.linear.x")  # what the nodes fill in


def _fields(msg: str) -> set[str]:
    return {line.split()[1] for line in (MSG / f"{msg}.msg").read_text().splitlines()
            if line.strip() and not line.startswith("#")}


def test_foxglove_layout_plots_fields_that_exist():
    """The layout's paths name topics and fields the nodes publish (tests/test_main_job.py
    loads it against a real demo bag: tests/helpers/foxglove_check.py)."""
    layout = json.loads((REPO / "docs" / "foxglove_layout.json").read_text())
    (script,) = layout["userNodes"].values()
    src = (REPO / "docs" / "foxglove_train_errors.ts").read_text()
    assert script["sourceCode"] == src  # the layout carries the reviewed script
    out_topic = re.search(r'export const output = "([^"]+)"', src).group(1)
    block = src.split("type Output = {")[1].split("\n};")[0]
    out_fields = set(re.findall(r"^  (\w+): ", block, re.M))
    inputs = re.findall(r'"(/train/[\w/]+)"', src.split("export const inputs")[1].split("];")[0])
    assert inputs == ["/train/ground_truth", "/train/estimate/robust", "/train/estimate/gsma",
                      "/train/estimate/kf"]
    for name in re.findall(r"\bm\.(\w+)", src):  # what the script reads from TrainState
        assert name in _fields("TrainState"), name
    plotted = []
    for panel, cfg in layout["configById"].items():
        if panel.startswith("DiagnosticSummary!"):
            assert cfg["topicToRender"] == "/diagnostics"
            plotted.append(("/diagnostics", ""))
            continue
        assert panel.startswith("Plot!") and cfg["title"]
        for path in cfg["paths"]:
            m = re.fullmatch(r'(/[\w/]+?)(\{source=="(\w+)"\})?\.([\w.]+)', path["value"])
            assert m, path["value"]
            topic, _, source, field = m.groups()
            if topic == out_topic:
                assert field in out_fields and source in SOURCES, path
            elif topic.startswith("/train/odom/"):
                assert field in ODOM_FIELDS, path
            else:
                assert topic.startswith("/train/"), topic
                assert field in _fields(TOPIC_MSG[topic[len("/train/"):]]), path
            plotted.append((topic, field))
    for want in [(out_topic, "position_error"), (out_topic, "velocity_error"),
                 ("/train/estimate/gsma", "braking_rate"), ("/train/estimate/kf", "braking_rate"),
                 ("/train/ground_truth", "braking_rate"), ("/diagnostics", "")] + \
            [(f"/train/odom/{n}", "twist.twist.linear.x") for n in ("robust", "gsma", "kf")]:
        assert want in plotted, want
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
