"""The commands that README.md and docs/*.md show cannot go stale.

The rule: every fenced block marked ```bash in README.md and docs/*.md is a list of commands
(lines joined at a trailing backslash, ``#`` comments dropped).

* Every command's program must exist and answer ``--help`` (exit 0), and every long option it
  uses (``--name``, up to a ``--ros-args``) must appear in that help text: a wrong executable,
  module, benchmark or option name fails the test.
* A block is also *run*, in order, from the repository's root, unless the line before it is an
  HTML comment starting with ``<!-- no-test`` (long runs: the demo, benchmarks, nodes, the
  test suite; a ROS installation from apt). Every run command must exit 0 within two minutes;
  paths under ``out/docs/`` are redirected to a fresh temporary directory per markdown file.

``./run exec CMD`` is run as ``CMD`` (this test already runs inside the project's environment),
``./run bench NAME`` as ``python benchmarks/bench_NAME.py``, ``./run demo`` as the main job's
module, ``ros2 run PKG EXE`` as the installed ``EXE`` of ``PKG``; ``./run test`` and ``./run
setup`` only have their sub-command checked against ``./run help``.
"""

from __future__ import annotations

import re
import shlex
import subprocess
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
DOCS = [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]
FENCE = re.compile(r"^```(\w*)\s*$")


def bash_blocks(path: Path) -> list[tuple[int, bool, list[str]]]:
    """[(line number, run it, [command, ...])] of the ```bash blocks of a markdown file."""
    out, lines = [], path.read_text().splitlines()
    i = 0
    while i < len(lines):
        m = FENCE.match(lines[i])
        if not m:
            i += 1
            continue
        j = i + 1
        while j < len(lines) and not lines[j].startswith("```"):
            j += 1
        if m.group(1) == "bash":
            k = i - 1
            while k >= 0 and not lines[k].strip():
                k -= 1
            run = not (k >= 0 and lines[k].strip().startswith("<!-- no-test"))
            out.append((i + 1, run, commands(lines[i + 1:j])))
        i = j + 1
    return out


def commands(lines: list[str]) -> list[str]:
    cmds, cur = [], ""
    for ln in lines:
        if ln.rstrip().endswith("\\"):
            cur += ln.rstrip()[:-1] + " "
            continue
        cur += ln
        words = shlex.split(cur, comments=True)
        if words:
            cmds.append(shlex.join(words))
        cur = ""
    return cmds


def translate(cmd: str) -> tuple[dict, list[str], int]:
    """(environment assignments, argv, n) with argv[:n] the program (help = argv[:n] + --help);
    n = 0: only the ./run sub-command is checked."""
    words = shlex.split(cmd)
    env = {}
    while words and re.fullmatch(r"[A-Z_][A-Z0-9_]*=\S*", words[0]):
        k, _, v = words.pop(0).partition("=")
        env[k] = v
    if words[:2] == ["./run", "exec"]:
        words = words[2:]
    elif words[:2] == ["./run", "bench"]:
        words = ["python", f"benchmarks/bench_{words[2]}.py", *words[3:]]
    elif words[:2] == ["./run", "demo"]:
        words = ["python", "-m", "train_bringup.main_job", *words[2:]]
    elif words[0] == "./run":
        return env, words, 0
    elif words[:2] == ["ros2", "run"]:
        from train_core.procs import resolve_executable

        exe = resolve_executable(words[2], words[3])
        assert exe is not None, f"{words[2]} {words[3]} is not an installed executable"
        words = [exe, *words[4:]]
    n = 3 if words[:2] == ["python", "-m"] else 2 if words[0] == "python" else 1
    return env, words, n


def _cases():
    for path in DOCS:
        for lineno, run, cmds in bash_blocks(path):
            for c in cmds:
                yield pytest.param(c, run, id=f"{path.name}:{lineno}:{c[:40]}")


CASES = list(_cases())
SUBCOMMANDS = None
HELP: dict = {}  # program (argv) -> its --help's CompletedProcess, once per test process


def _run_subcommands() -> set[str]:
    global SUBCOMMANDS
    if SUBCOMMANDS is None:
        out = subprocess.run(["bash", str(REPO / "run"), "help"], capture_output=True,
                             text=True, timeout=30, cwd=REPO).stdout
        SUBCOMMANDS = set(re.findall(r"^\s*\./run (\w+)", out, flags=re.M))
    return SUBCOMMANDS


def test_the_docs_show_commands_and_some_are_run():
    assert len(CASES) >= 10
    assert sum(1 for p in CASES if p.values[1]) >= 5
    assert any("csv2bag" in p.values[0] for p in CASES)


@pytest.mark.parametrize("cmd,run", CASES)
def test_program_and_options_exist(cmd, run, ros_env):
    _, argv, n = translate(cmd)
    if n == 0:
        assert argv[1] in _run_subcommands(), f"./run has no sub-command {argv[1]!r}"
        return
    key = tuple(argv[:n])
    if key not in HELP:  # many commands of the docs share a program: one --help each
        HELP[key] = subprocess.run([*key, "--help"], capture_output=True, text=True,
                                   timeout=120, cwd=REPO, env=ros_env)
    out = HELP[key]
    assert out.returncode == 0, f"{argv[:n]} --help: {out.stderr[-1500:]}"
    args = argv[n:]
    if "--ros-args" in args:
        args = args[:args.index("--ros-args")]
    for a in args:
        if a.startswith("--") and len(a) > 2:
            opt = a.split("=")[0]
            assert re.search(re.escape(opt) + r"\b", out.stdout), \
                f"{cmd}: {opt} is not an option of {argv[:n]}"


@pytest.mark.slow
def test_run_blocks_succeed(tmp_path, ros_env):
    """Run every runnable block's commands in order (they build on one another)."""
    ran = 0
    for path in DOCS:
        for lineno, run, cmds in bash_blocks(path):
            if not run:
                continue
            for cmd in cmds:
                env, argv, n = translate(cmd.replace("out/docs/", f"{tmp_path}/{path.stem}/"))
                if n == 0:
                    argv = ["bash", str(REPO / "run"), *argv[1:]]
                out = subprocess.run(argv, capture_output=True, text=True, timeout=120,
                                     cwd=REPO, env={**ros_env, **env})
                assert out.returncode == 0, \
                    f"{path.name}:{lineno}: {cmd}\n{out.stdout[-1000:]}\n{out.stderr[-1500:]}"
                ran += 1
    assert ran >= 5


NODE_CASES = [p for p in CASES if not p.values[1] and "--ros-args" in p.values[0]]


def _node_name(argv: list[str]) -> str:
    for a in argv:
        if a.startswith("__node:="):
            return a.split(":=", 1)[1]
    return argv[2].rsplit(".", 1)[-1] if argv[:2] == ["python", "-m"] else Path(argv[0]).name


def test_the_docs_show_node_commands():
    names = {_node_name(translate(p.values[0])[1]) for p in NODE_CASES}
    assert {"simulator", "robust_filter", "zone_controller", "kf_estimator", "player"} <= names


@pytest.mark.parametrize("cmd,run", NODE_CASES)
def test_node_command_starts_and_keeps_running(cmd, run, launch, ros_node):
    """A node the docs start by hand (not run to an end: a node runs until stopped) comes up
    in the ROS graph and is still running seconds later: a parameter it needs and the command
    lacks (an estimator's line_file) would end it at once. The command's TRAIN_ROS_DOMAIN_ID
    is not applied: the test session's isolated domain is."""
    _, argv, _ = translate(cmd)
    name = _node_name(argv)
    proc = launch.start(argv, name=name)

    def up():
        assert proc.poll() is None, f"{cmd}: exited with {proc.returncode}"
        return any(n == name for n, _ in ros_node.node.get_node_names_and_namespaces())

    ros_node.wait_until(up, timeout=60.0, what=f"node {name}")
    ros_node.spin_for(3.0)
    assert proc.poll() is None, f"{cmd}: exited with {proc.returncode} after starting"


def test_run_help_prints_the_header_only():
    out = subprocess.run(["bash", str(REPO / "run"), "help"], capture_output=True, text=True,
                         timeout=30, cwd=REPO)
    assert out.returncode == 0
    assert "set -" not in out.stdout and "#" not in out.stdout
    assert {"demo", "test", "setup", "shell", "exec", "bench"} <= _run_subcommands()


def test_a_wrong_option_is_caught(ros_env):
    """The check itself can fail: a misspelt option of a real tool is not in its help."""
    _, argv, n = translate("./run exec check_bag x --treshold a<=1")
    out = subprocess.run([*argv[:n], "--help"], capture_output=True, text=True, timeout=60,
                         env=ros_env)
    assert "--threshold" in out.stdout and "--treshold" not in out.stdout
    with pytest.raises(AssertionError):
        test_program_and_options_exist("./run exec check_bag x --treshold a<=1", False,
                                       ros_env)
