"""What the offline CLIs (identify, diagnose, fleet, check_bag) share: the exit-code ladder, the
project's progress bar (train_core.progress) and ``json.dumps``'s default for numpy values (a
diagnosis converts itself: ``Diagnosis.to_json``). Light on purpose: importing it must not pull
in the analyses (check_bag and identify start without the diagnose package)."""

from __future__ import annotations

import functools
import os
import sys
from pathlib import Path

import numpy as np
from train_core.config import show_config_warnings_on_one_line
from train_core.progress import Progress, track

# The exit-code ladder: 0 done (a diagnosis of "none" and a report listing failed bags
# included), 1 done but a check the user asked for failed, 2 the input is unusable (one line on
# stderr says what is missing or wrong).
EXIT_OK = 0
EXIT_CHECK_FAILED = 1
EXIT_UNUSABLE = 2
EXIT_INTERRUPTED = 130  # Ctrl-C (128 + SIGINT), as a shell reports it
EXIT_BROKEN_PIPE = 141  # the reader of stdout went away (128 + SIGPIPE)

# the project's one progress-bar style (train_core.progress), re-exported for the tools
__all__ = ["EXIT_BROKEN_PIPE", "EXIT_CHECK_FAILED", "EXIT_INTERRUPTED", "EXIT_OK",
           "EXIT_UNUSABLE", "INPUT_TOPICS", "Progress", "fail", "json_default", "one_line",
           "cannot_write", "cannot_write_there", "pipe_safe", "track", "unclosed", "unwritable"]

# the measured data's topics (docs/interfaces.md "Measured data")
INPUT_TOPICS = ("odometer", "balise", "control")
UNCLOSED = "(file tail)"  # train_core.bagio's key in Bag.skipped for a bag never closed


def one_line(exc) -> str:
    """An exception's message on one line."""
    return " ".join(str(exc).split())


def fail(prog: str, message: str) -> int:
    """Print ``prog: message`` (one line) on stderr; the exit code of unusable input."""
    print(f"{prog}: {one_line(message)}", file=sys.stderr)
    return EXIT_UNUSABLE


def json_default(o):
    """``json.dumps`` default for numpy values (arrays to lists, scalars to Python)."""
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    return str(o)


def unclosed(bag) -> str:
    """For an error message: " (the bag was not closed: ...; the repair command)" when ``bag``
    (a train_core.bagio Bag, its ``skipped`` dict, or None) was never closed by its recorder,
    else "". A killed recorder is the usual reason a topic or the run's end is missing."""
    skipped = bag if isinstance(bag, dict) else getattr(bag, "skipped", None) or {}
    why = skipped.get(UNCLOSED)
    return f" ({why})" if why else ""


# an extra key in a file the tools read is one line on stderr (train_core.config)
show_config_warnings_on_one_line()


def pipe_safe(main):
    """A tool's ``main`` that stops quietly when the reader of its output goes away
    (``diagnose ... | head -1``), as Unix tools do: exit status 141 (SIGPIPE), no traceback.
    stdout is pointed at /dev/null so that the interpreter's last flush does not fail again."""
    @functools.wraps(main)
    def run(argv=None) -> int:
        try:
            return main(argv)
        except BrokenPipeError:
            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, sys.stdout.fileno())
            return EXIT_BROKEN_PIPE
    return run


def unwritable(out: Path) -> str:
    """Why outputs cannot go to the directory ``out`` ("" if they can), without creating it:
    a file in the way, or a nearest existing folder that cannot be written. A tool checks it
    before its analysis, which is then not run to be lost."""
    if out.exists() and not out.is_dir():
        return "is a file"
    p = out
    while not p.exists() and p != p.parent:
        p = p.parent
    if not p.is_dir():
        return f"{p} is a file"
    if not os.access(p, os.W_OK | os.X_OK):
        return f"cannot write in {p}"
    return ""


def cannot_write_there(out, exc: OSError) -> str:
    """What to say when outputs could not be written to ``out`` (--out)."""
    return f"--out {out}: cannot write there ({exc.strerror or exc})"


def cannot_write(prog: str, out, exc: OSError) -> int:
    """:func:`fail` for outputs that could not be written to ``out`` (--out)."""
    return fail(prog, cannot_write_there(out, exc))
