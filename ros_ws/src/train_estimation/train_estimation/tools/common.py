"""What the offline CLIs (identify, diagnose, fleet, check_bag) share: the exit-code ladder, a
progress bar and the conversion of results to JSON types."""

from __future__ import annotations

import sys

import numpy as np

from train_estimation.core.diagnose.result import jsonable

# The exit-code ladder: 0 done (a diagnosis of "none" and a report listing failed bags
# included), 1 done but a check the user asked for failed, 2 the input is unusable (one line on
# stderr says what is missing or wrong).
EXIT_OK = 0
EXIT_CHECK_FAILED = 1
EXIT_UNUSABLE = 2

__all__ = ["EXIT_CHECK_FAILED", "EXIT_OK", "EXIT_UNUSABLE", "Progress", "fail", "json_default",
           "jsonable", "one_line"]


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


class Progress:
    """A progress callback ``(step, total, what)`` drawn by tqdm on stderr; the bar appears at
    the first step (nothing is drawn for input refused before it) and closes at the last."""

    def __init__(self, label: str, what_width: int = 30):
        self.label, self.what_width = label, what_width
        self.bar = None

    def __call__(self, step: int, total: int, what: str) -> None:
        from tqdm import tqdm

        if self.bar is None:
            self.bar = tqdm(total=total, desc=self.label, file=sys.stderr, leave=True,
                            bar_format="{desc} [{bar:30}] {percentage:5.1f}% {postfix}")
        self.bar.set_postfix_str(f"{what:<{self.what_width}}", refresh=False)
        self.bar.update(max(min(step, total) - self.bar.n, 0))
        if step >= total:
            self.bar.close()
            self.bar = None
