"""The project's one progress-bar style (tqdm on stderr), for the offline tools, the fleet
simulator and the benchmarks alike: ``label [#####     ] 12/40  30% 00:41<01:35 what``.

- :func:`track` wraps an iterable (a loop over seeds, cases, futures as they complete);
- :class:`Progress` is a callback ``(step, total, what)`` for code that reports its own steps
  (identify, diagnose, the fleet writer): the bar appears at the first step, so nothing is
  drawn for input refused before it, and closes at the last.

Bars are drawn on stderr, so a benchmark's tables on stdout stay clean when redirected.
"""

from __future__ import annotations

import sys
from collections.abc import Iterable

BAR_FORMAT = ("{desc} [{bar:30}] {n_fmt}/{total_fmt} {percentage:3.0f}% "
              "{elapsed}<{remaining} {postfix}")

__all__ = ["BAR_FORMAT", "Progress", "bar", "track"]


def bar(total: int | None, label: str, disable: bool = False):
    """A tqdm bar in the project's style (use as a context manager, ``.update(n)``)."""
    from tqdm import tqdm

    return tqdm(total=total, desc=label, file=sys.stderr, leave=True, bar_format=BAR_FORMAT,
                disable=disable, dynamic_ncols=True)


def track(items: Iterable, label: str, total: int | None = None, disable: bool = False):
    """``items`` with a progress bar of ``total`` steps (default ``len(items)``)."""
    if total is None:
        try:
            total = len(items)  # type: ignore[arg-type]
        except TypeError:
            total = None
    with bar(total, label, disable) as b:
        for x in items:
            yield x
            b.update(1)


class Progress:
    """A progress callback ``(step, total, what)`` drawn in the project's style on stderr."""

    def __init__(self, label: str, what_width: int = 30):
        self.label, self.what_width = label, what_width
        self.bar = None

    def __call__(self, step: int, total: int, what: str) -> None:
        if self.bar is None:
            self.bar = bar(total, self.label)
        self.bar.set_postfix_str(f"{what:<{self.what_width}}", refresh=False)
        self.bar.update(max(min(step, total) - self.bar.n, 0))
        if step >= total:
            self.bar.close()
            self.bar = None
