"""report.html in a real browser: headless Chromium lays a page out and measures it
(``page_metrics``: its height, where each element ends, what overflows sideways) or renders it
into a PNG (``screenshot``), for ``report_html --screenshot``, scripts/check_report.sh and the
layout tests. Debian's ``chromium`` package, or a ``chromium`` on PATH.
"""

from __future__ import annotations

import html
import json
import re
from pathlib import Path

CHROMIUM = "/usr/bin/chromium"  # Debian's package (apt-get install chromium)
NO_CHROMIUM = (f"{CHROMIUM} is not installed: install Debian's package with "
               "`apt-get update && apt-get install -y chromium` (./run setup does it where it "
               "runs as root with apt-get)")


def chromium_path() -> str | None:
    """Debian's Chromium, or a ``chromium`` on PATH; None when there is none."""
    import shutil

    return CHROMIUM if Path(CHROMIUM).is_file() else shutil.which("chromium")


def _chromium(args: list, chromium: str | None, timeout: float):
    import shutil
    import subprocess
    import tempfile

    exe = chromium or chromium_path()
    if not exe:
        raise OSError(NO_CHROMIUM)
    profile = tempfile.mkdtemp(prefix="report_html_chromium_")
    try:
        # a throw-away profile, no network services, no GPU, no sandbox so that it runs as root
        # in a container
        cmd = [exe, "--headless", "--no-sandbox", "--disable-gpu",
               "--disable-background-networking", "--disable-component-update",
               "--disable-sync", "--no-first-run", "--hide-scrollbars",
               f"--user-data-dir={profile}", *args]
        return subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)
    finally:
        shutil.rmtree(profile, ignore_errors=True)


# Measures the laid-out page and writes the figures into the DOM, which --dump-dom prints: the
# page's height and width, and every element wider than the window or whose content is wider
# than its box (an overflow the reader has to scroll sideways for, or does not see at all).
_MEASURE = """<script>
window.addEventListener('load', function () {
  var W = document.documentElement.clientWidth, bad = [];
  document.querySelectorAll('body *').forEach(function (el) {
    var r = el.getBoundingClientRect();
    if (r.right > W + 1 || el.scrollWidth > el.clientWidth + 1 && el.clientWidth > 0)
      bad.push(el.tagName.toLowerCase() + (el.id ? '#' + el.id : '') + ' ' +
               Math.round(r.right) + '/' + el.scrollWidth + '>' + el.clientWidth);
  });
  var bottom = {};
  document.querySelectorAll('[id]').forEach(function (el) {
    bottom[el.id] = Math.round(el.getBoundingClientRect().bottom + window.scrollY);
  });
  var out = document.createElement('pre');
  out.textContent = JSON.stringify({height: document.documentElement.scrollHeight,
    bottom: bottom, width: document.documentElement.scrollWidth, window: W,
    overflowing: bad.slice(0, 20), n_overflowing: bad.length});
  out.id = 'page-metrics';
  document.body.appendChild(out);
});
</script>"""


def page_metrics(page: Path, width: int = 1280, chromium: str | None = None,
                 timeout: float = 120.0) -> dict:
    """Lay ``page`` out in headless Chromium at ``width`` px: {"height": px, "width": px,
    "window": px, "bottom": {element id: px from the top of the page}, "overflowing": [up to
    20 elements], "n_overflowing": n}. The page is
    measured from a copy with a measuring script (the page itself has none)."""
    import tempfile

    text = Path(page).read_text(encoding="utf-8")
    with tempfile.TemporaryDirectory(prefix="report_html_measure_") as d:
        probe = Path(d) / "page.html"
        probe.write_text(text.replace("</body>", _MEASURE + "</body>", 1), encoding="utf-8")
        res = _chromium([f"--window-size={width},900", "--virtual-time-budget=10000",
                         "--dump-dom", probe.as_uri()], chromium, timeout)
    m = re.search(r'<pre id="page-metrics">(.*?)</pre>', res.stdout, re.S)
    if not m:
        raise OSError(f"chromium measured nothing (exit {res.returncode}: "
                      f"{res.stderr.strip().splitlines()[-1:] or ''})")
    return json.loads(html.unescape(m.group(1)))


def screenshot(page: Path, png: Path, size=(1280, None), chromium: str | None = None,
               timeout: float = 120.0) -> Path:
    """Render ``page`` in headless Chromium into ``png``: ``size`` = (width, height) px; a
    height of None takes the whole page (measured first)."""
    png = Path(png).resolve()
    png.unlink(missing_ok=True)
    w, h = size
    if h is None:
        h = int(page_metrics(page, w, chromium, timeout)["height"])
    res = _chromium([f"--window-size={w},{h}", f"--screenshot={png}",
                     Path(page).resolve().as_uri()], chromium, timeout)
    if not png.is_file():
        raise OSError(f"chromium wrote no screenshot (exit {res.returncode}: "
                      f"{res.stderr.strip().splitlines()[-1:] or ''})")
    return png
