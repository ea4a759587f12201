"""One self-contained ``report.html`` from an output directory of `diagnose` or `fleet`.

    python -m train_estimation.tools.report_html DIR [--screenshot PNG]

The page is what a reader forwards: the verdict first, then the evidence, every plot embedded
as a ``data:image/png;base64`` URI, the styles inline, no script and no external address, so it
opens the same from a mail attachment, a file share or a machine without a network.

- a `diagnose` directory (``report.json``): the cause and its parameters, the held-out gain and
  any unexplained structure first; then the ranking, the untestable causes, the evidence, every
  other field of report.json, then the plots. Lists of records become tables over the union of
  their keys and mappings become key/value tables, so fields added to report.json appear
  without a change here.
- a `fleet` directory (``report.md``, which already puts the verdict first): that report
  rendered (headings, tables, lists, emphasis) with its images embedded where it references
  them, then any plot it does not reference.
"""

from __future__ import annotations

import base64
import html
import json
import re
import sys
from pathlib import Path

__all__ = ["render_diagnose", "render_fleet", "screenshot", "write_report_html"]

STYLE = """
body{font-family:system-ui,-apple-system,'Segoe UI',Roboto,sans-serif;margin:0 auto;
max-width:1100px;padding:1em 1.5em;color:#222;line-height:1.4}
h1{font-size:1.5em;margin-bottom:.2em}h2{font-size:1.2em;border-bottom:1px solid #ccc;
margin-top:1.6em}h3{font-size:1.05em}
.verdict{border-left:6px solid #2b6cb0;background:#eef4fb;padding:.6em 1em;margin:1em 0}
.verdict.found{border-color:#c05621;background:#fdf2e9}
.verdict.none{border-color:#2f855a;background:#eefaf2}
.verdict .cause{font-size:1.4em;font-weight:600}
table{border-collapse:collapse;margin:.5em 0 1em;font-size:.9em}
.wide{overflow-x:auto}
th,td{border:1px solid #ccc;padding:.25em .5em;text-align:left;vertical-align:top}
th{background:#f3f3f3}td.num{text-align:right;font-variant-numeric:tabular-nums}
figure{margin:1em 0}figure img{max-width:100%;border:1px solid #ddd}
figcaption{font-size:.85em;color:#555}
code,pre{background:#f6f6f6;font-size:.88em}pre{padding:.5em;overflow-x:auto}
.muted{color:#666;font-size:.85em}
"""

# report.json fields shown in the verdict or in their own section, in this order; any other
# field follows them generically
_DIAGNOSE_SECTIONS = (("unexplained", "Unexplained structure"),
                      ("ranking", "Ranking of the causes tested"), ("gain", "Held-out gain"),
                      ("plots", "Plots"), ("untestable", "Causes the data cannot test"),
                      ("evidence", "Evidence"))

# the plots that tell the story first (the before/after replay, then where the residual is);
# any other plot follows in name order
_PLOT_ORDER = ("replay.png", "residual_position.png", "residual_speed.png", "speed_trace.png")


def _e(x) -> str:
    return html.escape(str(x), quote=True)


def _num(v) -> str:
    if isinstance(v, bool) or v is None:
        return "&ndash;" if v is None else str(v).lower()
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        return f"{v:.4g}"
    return _e(v)


def _inline(v) -> str:
    """A value inside a table cell: scalars as text, short lists inline, the rest nested."""
    if isinstance(v, dict):
        if not v:
            return "&ndash;"
        if all(not isinstance(x, (dict, list)) or len(x) <= 4 for x in v.values()):
            # a handful of parameters reads best on one line
            return "<br>".join(f"{_e(k)} = {_inline(x)}" for k, x in v.items())
        return table_of(v)
    if isinstance(v, list):
        if v and all(isinstance(x, dict) for x in v):
            return table_of(v)
        flat = [_inline(x) for x in v[:12]]
        more = f", &hellip; ({len(v)} in all)" if len(v) > 12 else ""
        return "[" + ", ".join(flat) + more + "]"
    return _num(v)


def _cell(v) -> str:
    cls = ' class="num"' if isinstance(v, (int, float)) and not isinstance(v, bool) else ""
    return f"<td{cls}>{_inline(v)}</td>"


def table_of(data) -> str:
    """A table of JSON data: a list of records over the union of their keys (first-seen
    order), a mapping of records as rows named by their key, any other mapping as key/value."""
    if isinstance(data, list):
        if not data:
            return '<p class="muted">(none)</p>'
        if not all(isinstance(r, dict) for r in data):
            return "<p>" + _inline(data) + "</p>"
        keys: list = []
        for r in data:
            keys += [k for k in r if k not in keys]
        head = "".join(f"<th>{_e(k)}</th>" for k in keys)
        rows = "".join("<tr>" + "".join(_cell(r.get(k)) for k in keys) + "</tr>" for r in data)
        return f'<div class="wide"><table><tr>{head}</tr>{rows}</table></div>'
    if isinstance(data, dict):
        if data and all(isinstance(v, dict) for v in data.values()):
            return table_of([{"": k, **v} for k, v in data.items()])
        rows = "".join(f"<tr><th>{_e(k)}</th>{_cell(v)}</tr>" for k, v in data.items())
        return f"<table>{rows}</table>"
    return f"<p>{_inline(data)}</p>"


def img_uri(path: Path) -> str:
    """A PNG as a data URI (the page holds the image itself)."""
    return "data:image/png;base64," + base64.b64encode(path.read_bytes()).decode("ascii")


def _figure(path: Path) -> str:
    return (f'<figure><img src="{img_uri(path)}" alt="{_e(path.name)}">'
            f"<figcaption>{_e(path.name)}</figcaption></figure>")


def _page(title: str, body: str) -> str:
    return (f'<!DOCTYPE html>\n<html lang="en"><head><meta charset="utf-8">'
            f'<meta name="viewport" content="width=device-width, initial-scale=1">'
            f"<title>{_e(title)}</title><style>{STYLE}</style></head>\n<body>\n{body}\n"
            "</body></html>\n")


# ------------------------------------------------------------------------------------------------
# diagnose
# ------------------------------------------------------------------------------------------------

def _verdict(rep: dict) -> str:
    cause = rep.get("cause", "?")
    kind = "none" if cause == "none" else "found"
    parts = [f'<div class="verdict {kind}" id="verdict"><div>Verdict</div>'
             f'<div class="cause">cause: {_e(cause)}</div>']
    if rep.get("parameters"):
        parts.append(table_of(rep["parameters"]))
    top = next((r for r in rep.get("ranking") or [] if r.get("cause") == cause), None)
    for key in ("status", "why"):
        if top is not None and top.get(key) not in (None, "", []):
            parts.append(f"<div>{_e(key)}: {_inline(top[key])}</div>")
    g = rep.get("gain") or {}
    if g.get("before") is not None and g.get("after") is not None:
        parts.append(f"<div>held-out gain: {_num(g['before'])} &rarr; {_num(g['after'])} "
                     f'<span class="muted">({_e(g.get("metric", ""))})</span></div>')
    unexpl = rep.get("unexplained")
    if isinstance(unexpl, list) and unexpl:
        parts.append(f"<div><b>{len(unexpl)} unexplained residual structure"
                     f"{'s' if len(unexpl) > 1 else ''}</b>: see below</div>")
    elif isinstance(unexpl, list):
        parts.append("<div>nothing left unexplained</div>")
    parts.append("</div>")
    return "".join(parts)


def render_diagnose(out: Path) -> str:
    """report.html's text for a diagnose output directory."""
    rep = json.loads((out / "report.json").read_text())
    body = [f"<h1>diagnose: {_e(out.name)}</h1>", _verdict(rep)]
    shown = {"cause", "parameters"}
    for key, title in _DIAGNOSE_SECTIONS:
        if key == "plots":
            pngs = sorted(out.glob("*.png"), key=lambda p: (
                _PLOT_ORDER.index(p.name) if p.name in _PLOT_ORDER else len(_PLOT_ORDER), p.name))
            if pngs:
                body.append('<h2 id="plots">Plots</h2>' + "".join(_figure(p) for p in pngs))
        elif key in rep:
            body.append(f'<h2 id="{_e(key)}">{_e(title)}</h2>{table_of(rep[key])}')
            shown.add(key)
    for key, val in rep.items():
        if key not in shown:
            body.append(f'<h2 id="{_e(key)}">{_e(key)}</h2>{table_of(val)}')
    model = out / "model"
    if model.is_dir():
        files = "".join(f"<h3>{_e(f.name)}</h3><pre>{_e(f.read_text())}</pre>"
                        for f in sorted(model.glob("*.yaml")))
        body.append(f'<h2 id="model">The extended model (model/)</h2>{files}')
    return _page(f"diagnose: {rep.get('cause', '?')}", "\n".join(body))


# ------------------------------------------------------------------------------------------------
# fleet (report.md)
# ------------------------------------------------------------------------------------------------

_IMG = re.compile(r"!\[([^\]]*)\]\(([^)\s]+)\)")
_LINK = re.compile(r"\[([^\]]+)\]\(([^)\s]+)\)")


def _md_inline(text: str, out: Path, used: set) -> str:
    """Emphasis, code and images of one line of the report's Markdown (escaped first)."""
    imgs: list = []

    def keep(m):
        imgs.append(m)
        return f"\x00{len(imgs) - 1}\x00"

    def img(m):
        p = out / m.group(2)
        if p.is_file() and p.suffix == ".png":
            used.add(p.name)
            return f'<img src="{img_uri(p)}" alt="{_e(m.group(1))}">'
        return _e(m.group(1))

    t = _e(_IMG.sub(keep, text))
    t = re.sub(r"`([^`]+)`", r"<code>\1</code>", t)
    t = re.sub(r"\*\*([^*]+)\*\*", r"<b>\1</b>", t)
    t = re.sub(r"(?<![\w*])\*([^*]+)\*(?![\w*])", r"<i>\1</i>", t)
    t = _LINK.sub(r"\1", t)  # links to local files: their text (the page stands alone)
    return re.sub("\x00(\\d+)\x00", lambda m: img(imgs[int(m.group(1))]), t)


def markdown_html(md: str, out: Path, used: set) -> str:
    """The Markdown fleet writes (ATX headings, pipe tables, "-" lists, paragraphs)."""
    html_lines, para, lst, table = [], [], [], []

    def flush():
        if para:
            html_lines.append("<p>" + " ".join(para) + "</p>")
            para.clear()
        if lst:
            html_lines.append("<ul>" + "".join(f"<li>{x}</li>" for x in lst) + "</ul>")
            lst.clear()
        if table:
            cells = [[c.strip() for c in r.strip().strip("|").split("|")] for r in table]
            body = [r for r in cells[1:] if not all(re.fullmatch(r":?-+:?", c) for c in r)]
            head = "".join(f"<th>{_md_inline(c, out, used)}</th>" for c in cells[0])
            rows = "".join("<tr>" + "".join(f"<td>{_md_inline(c, out, used)}</td>" for c in r)
                           + "</tr>" for r in body)
            html_lines.append(f"<table><tr>{head}</tr>{rows}</table>")
            table.clear()

    for line in md.splitlines():
        s = line.rstrip()
        if s.startswith("|"):
            if para or lst:
                flush()
            table.append(s)
            continue
        if table:
            flush()
        m = re.match(r"(#{1,6})\s+(.*)", s)
        if m:
            flush()
            n = len(m.group(1))
            html_lines.append(f"<h{n}>{_md_inline(m.group(2), out, used)}</h{n}>")
        elif re.match(r"\s*[-*]\s+", s):
            if para:
                flush()
            lst.append(_md_inline(re.sub(r"^\s*[-*]\s+", "", s), out, used))
        elif not s.strip():
            flush()
        elif lst and line.startswith("  "):
            lst[-1] += " " + _md_inline(s.strip(), out, used)
        else:
            if lst:
                flush()
            para.append(_md_inline(s, out, used))
    flush()
    return "\n".join(html_lines)


def render_fleet(out: Path) -> str:
    """report.html's text for a fleet output directory (its report.md, images embedded)."""
    used: set = set()
    body = markdown_html((out / "report.md").read_text(), out, used)
    # the first paragraphs after the title are fleet's verdict: mark them as such
    body = body.replace("</h1>\n", '</h1>\n<div class="verdict" id="verdict">', 1)
    if 'id="verdict"' in body:
        i = body.find("<h2>")
        body = body[:i] + "</div>\n" + body[i:] if i >= 0 else body + "</div>"
    rest = [p for p in sorted(out.glob("*.png")) if p.name not in used]
    if rest:
        body += '\n<h2 id="plots">Plots</h2>' + "".join(_figure(p) for p in rest)
    return _page(f"fleet: {out.name}", body)


def write_report_html(out: str | Path, kind: str | None = None) -> Path:
    """Write DIR/report.html for a diagnose (report.json) or fleet (report.md) directory;
    ``kind`` ("diagnose" or "fleet") says which, else the files present decide."""
    out = Path(out)
    if kind == "diagnose" or (kind is None and (out / "report.json").is_file()):
        text = render_diagnose(out)
    elif kind == "fleet" or (kind is None and (out / "report.md").is_file()):
        text = render_fleet(out)
    else:
        raise FileNotFoundError(f"{out}: neither report.json (diagnose) nor report.md (fleet)")
    path = out / "report.html"
    path.write_text(text, encoding="utf-8")
    return path


CHROMIUM = "/usr/bin/chromium"  # Debian's package (apt-get install chromium)


def screenshot(page: Path, png: Path, size=(1200, 1800), chromium: str = CHROMIUM,
               timeout: float = 120.0) -> Path:
    """Render ``page`` in headless Chromium (a throw-away profile, no network services, no GPU,
    no sandbox so that it runs as root in a container) into ``png``, the window's top
    ``size`` (px)."""
    import shutil
    import subprocess
    import tempfile

    png = Path(png).resolve()
    png.unlink(missing_ok=True)
    profile = tempfile.mkdtemp(prefix="report_html_chromium_")
    try:
        cmd = [chromium, "--headless", "--no-sandbox", "--disable-gpu",
               "--disable-background-networking", "--disable-component-update",
               "--disable-sync", "--no-first-run", "--hide-scrollbars",
               f"--user-data-dir={profile}", f"--window-size={size[0]},{size[1]}",
               f"--screenshot={png}", Path(page).resolve().as_uri()]
        res = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)
    finally:
        shutil.rmtree(profile, ignore_errors=True)
    if not png.is_file():
        raise OSError(f"{chromium} wrote no screenshot (exit {res.returncode}: "
                      f"{res.stderr.strip().splitlines()[-1:] or ''})")
    return png


def main(argv=None) -> int:
    import argparse

    p = argparse.ArgumentParser(prog="report_html", description=__doc__.splitlines()[0])
    p.add_argument("dir", help="an output directory of diagnose or fleet")
    p.add_argument("--screenshot", metavar="PNG",
                   help="also render report.html in headless Chromium into PNG")
    p.add_argument("--size", default="1200x1800", help="screenshot size WxH px (1200x1800)")
    p.add_argument("--chromium", default=CHROMIUM, help=f"browser binary ({CHROMIUM})")
    args = p.parse_args(argv)
    try:
        page = write_report_html(args.dir)
        print(f"wrote {page}")
        if args.screenshot:
            w, h = (int(v) for v in args.size.lower().split("x"))
            print(f"wrote {screenshot(page, Path(args.screenshot), (w, h), args.chromium)}")
    except (OSError, ValueError, json.JSONDecodeError) as exc:
        print(f"report_html: {' '.join(str(exc).split())}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
