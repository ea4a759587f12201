"""One self-contained ``report.html`` from an output directory of `diagnose` or `fleet`.

    python -m train_estimation.tools.report_html DIR [--screenshot PNG]

The page is what a reader forwards: the verdict first, then the evidence, every plot embedded
as a ``data:`` URI (diagnose's SVG figures, fleet's PNGs), the styles inline, no script and no
external address, so it opens the same from a mail attachment, a file share or a machine
without a network.

- a `diagnose` directory (``report.json``, ``inputs.json``), from the Jinja2 template
  ``templates/diagnose_report.html.j2``: a header (bag, line, train, data, date), the verdict
  (each confirmed cause's parameters with units and standard errors, its caveats, the held-out
  gain, whether anything is left unexplained) on the first screen; then the unexplained
  structure, the ranking, the untestable causes, the plots, the evidence per cause in rows, and
  an appendix with the model's details (the confirmation's settings, any other field of
  report.json, the extended model's files). Numbers have 4 significant figures.
- a `fleet` directory (``report.md``, which already puts the verdict first): that report
  rendered (headings, tables, lists, emphasis) with its images embedded where it references
  them, then any plot it does not reference.
"""

from __future__ import annotations

import base64
import html
import json
import math
import re
import sys
from pathlib import Path

__all__ = ["render_diagnose", "render_fleet", "write_report_html"]

TEMPLATES = Path(__file__).resolve().parent / "templates"

# Units of the causes' parameters (docs/interfaces.md, the causes' table); a parameter not
# listed is shown without a unit
UNITS = {
    "start": "m", "end": "m", "permille": "per mille",
    "a": "N", "b": "N/(m/s)", "c": "N/(m/s)^2",
    "f_start": "-", "f_end": "-", "scale": "-", "depths": "-", "factor": "-",
    "intervals": "s", "delay": "s", "mass": "kg", "drift": "s/s", "p_spec": "m^2/s^3",
    "p_good_bad": "per sample", "p_bad_good": "per sample", "loss_good": "-", "loss_bad": "-",
}

# the plots that tell the story first (the before/after replay, then where the residual is);
# any other plot follows in name order
_PLOT_ORDER = ("replay.svg", "residual_position.svg", "residual_speed.svg", "speed_trace.svg")

# report.json fields the diagnose page shows in their own place; any other field goes to the
# appendix, so fields added to report.json appear without a change here
_DIAGNOSE_SHOWN = ("cause", "parameters", "ranking", "unexplained", "untestable", "evidence",
                   "gain")


def _e(x) -> str:
    return html.escape(str(x), quote=True)


def sig4(v) -> str:
    """A number as a reader takes it in: 4 significant figures, no exponent between 1e-3 and
    1e6 (2929.8132 -> 2930, 0.012345 -> 0.01235), an exponent outside; integers as they are."""
    if isinstance(v, bool) or v is None:
        return "&ndash;" if v is None else str(v).lower()
    if isinstance(v, int):
        return str(v)
    if not isinstance(v, float):
        return _e(v)
    if not math.isfinite(v):
        return str(v)
    if v == 0.0:
        return "0"
    mag = math.floor(math.log10(abs(v)))
    if -3 <= mag < 6:
        r = round(v, 3 - mag)
        return f"{r:.{max(0, 3 - mag)}f}"
    return f"{v:.3e}"


_num = sig4


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
        return f"<table><tr>{head}</tr>{rows}</table>"
    if isinstance(data, dict):
        rows = "".join(f"<tr><th>{_e(k)}</th>{_cell(v)}</tr>" for k, v in data.items())
        return f"<table>{rows}</table>"
    return f"<p>{_inline(data)}</p>"


_MIME = {".png": "image/png", ".svg": "image/svg+xml"}


def img_uri(path: Path) -> str:
    """A PNG or SVG image as a data URI (the page holds the image itself)."""
    return (f"data:{_MIME[path.suffix]};base64,"
            + base64.b64encode(path.read_bytes()).decode("ascii"))


def _figure(path: Path) -> str:
    return (f'<figure><img src="{img_uri(path)}" alt="{_e(path.name)}">'
            f"<figcaption>{_e(path.name)}</figcaption></figure>")


def _env():
    import jinja2

    return jinja2.Environment(loader=jinja2.FileSystemLoader(str(TEMPLATES)),
                              autoescape=True, undefined=jinja2.StrictUndefined,
                              trim_blocks=True, lstrip_blocks=True)


def _page(title: str, body: str) -> str:
    from markupsafe import Markup

    return _env().get_template("page.html.j2").render(title=title, body=Markup(body))


# ------------------------------------------------------------------------------------------------
# diagnose
# ------------------------------------------------------------------------------------------------

def with_unit(name: str, v) -> str:
    """A parameter's value with its unit (plain text, escaped by the template)."""
    unit = UNITS.get(name, "")
    unit = "" if unit in ("", "-") else f" {unit}"
    if isinstance(v, list):
        inner = ", ".join(with_unit("", x) if not isinstance(x, list) else
                          "[" + ", ".join(html.unescape(sig4(y)) for y in x) + "]"
                          for x in v[:8])
        more = f", ... ({len(v)} in all)" if len(v) > 8 else ""
        return f"[{inner}{more}]{unit}"
    return html.unescape(sig4(v)) + unit


def params_text(p: dict) -> str:
    return "; ".join(f"{k} = {with_unit(k, v)}" for k, v in (p or {}).items()) or "-"


def _evidence_value(cause: str, key: str, v) -> str:
    """One field of a cause's evidence as text: a fit or standard errors as parameter = value
    unit, other numbers to 4 significant figures."""
    if isinstance(v, dict):
        if all(not isinstance(x, dict) for x in v.values()):
            return params_text(v)
        return "; ".join(f"{k}: {_evidence_value(cause, k, x)}" for k, x in v.items())
    if isinstance(v, list):
        return with_unit(key, v)
    return html.unescape(sig4(v))


def _load_inputs(out: Path) -> dict:
    """inputs.json's mapping; a value of another kind than diagnose writes (a number for the
    bag's path: an edited file) is left out, shown as not recorded."""
    try:
        d = json.loads((out / "inputs.json").read_text(encoding="utf-8-sig"))
    except (OSError, ValueError):
        return {}
    if not isinstance(d, dict):
        return {}
    return {k: v for k, v in d.items() if not (k in ("bag", "data", "date")
                                               and not isinstance(v, str))}


# report.json's fields this page reads and the kind each must have (diagnose writes them so; a
# file edited or forwarded by hand may not): a list of numbers (or null) or a mapping
_SPANS = ("where", "when", "speed")


def _load_report(out: Path) -> dict:
    """report.json, its fields of the kinds this page reads; another kind is a ValueError
    naming the field (one line, exit 2), not a traceback in the template."""
    f = out / "report.json"
    rep = json.loads(f.read_text(encoding="utf-8-sig"))

    def bad(where, what, v):
        return ValueError(f"{f}: {where} should be {what}, not {type(v).__name__} {v!r:.40} "
                          f"(an edited report? diagnose --out writes it again)")

    if not isinstance(rep, dict):
        raise bad("the top level", "a mapping", rep)
    if rep.get("parameters") is not None and not isinstance(rep["parameters"], dict):
        raise bad("parameters", "a mapping", rep["parameters"])
    if rep.get("ranking") is not None and not isinstance(rep["ranking"], list):
        raise bad("ranking", "a list", rep["ranking"])
    for i, r in enumerate(rep.get("ranking") or []):
        if isinstance(r, dict) and r.get("parameters") is not None and \
                not isinstance(r["parameters"], dict):
            raise bad(f"ranking[{i}].parameters", "a mapping", r["parameters"])
    for i, u in enumerate(rep.get("unexplained") or []):
        if not isinstance(u, dict):
            continue
        for k in _SPANS:
            v = u.get(k)
            if v is not None and not (isinstance(v, list) and all(
                    isinstance(x, int | float) and not isinstance(x, bool) for x in v)):
                raise bad(f"unexplained[{i}].{k}", "a list of numbers", v)
        if u.get("size") is not None and not isinstance(u["size"], int | float):
            raise bad(f"unexplained[{i}].size", "a number", u["size"])
    return rep


def diagnose_context(out: Path) -> dict:
    """What diagnose_report.html.j2 shows, every number formatted and with its unit."""
    from train_estimation.tools.diagnose_unexplained import unexplained_line, unexplained_size

    rep = _load_report(out)
    inp = _load_inputs(out)
    cause = rep.get("cause", "?")
    ranking = [r for r in rep.get("ranking") or [] if isinstance(r, dict)]
    ev = rep.get("evidence") if isinstance(rep.get("evidence"), dict) else {}
    checks = (((ev.get("_model") or {}).get("confirmation") or {}).get("checks") or {})

    def caveats(name):
        c = (checks.get(name) or {}).get("caveat")
        return [c] if isinstance(c, str) and c else ([str(x) for x in c] if c else [])

    def se_of(name, key):
        se = ((ev.get(name) or {}).get("std_errors") or {})
        v = se.get(key) if isinstance(se, dict) else None
        return with_unit(key, v) if isinstance(v, (int, float)) else "-"

    confirmed = [r for r in ranking if r.get("status") == "confirmed" and r.get("cause") != "none"]
    if not confirmed and rep.get("parameters"):
        confirmed = [{"cause": cause, "parameters": rep["parameters"], "status": ""}]
    blocks = [{"cause": r.get("cause"), "status": r.get("status") or "",
               "params": [{"name": k, "value": html.unescape(with_unit("", v)) if not
                           isinstance(v, list) else with_unit("", v),
                           "unit": UNITS.get(k, ""), "se": se_of(r.get("cause"), k)}
                          for k, v in (r.get("parameters") or {}).items()],
               "caveats": caveats(r.get("cause"))} for r in confirmed]
    unexpl = [u for u in rep.get("unexplained") or [] if isinstance(u, dict)]
    if cause == "none":
        sentence = "Nothing significant: no listed cause is confirmed and nothing is left over."
    elif cause == "unexplained":
        sentence = ("No listed cause is confirmed, and the residuals hold structure that no "
                    "listed cause explains (below).")
    else:
        sentence = (f"{len(confirmed)} cause{'s' if len(confirmed) != 1 else ''} confirmed "
                    "(supported by the score and by the check on data held out from the fit).")
    g = rep.get("gain") or {}
    gain = ""
    if isinstance(g, dict) and g.get("before") is not None and g.get("after") is not None:
        gain = (f"{html.unescape(sig4(g['before']))} -> {html.unescape(sig4(g['after']))} "
                f"({g.get('metric', '')})")
    left = (f"{len(unexpl)} unexplained residual structure{'s' if len(unexpl) != 1 else ''}: "
            "see below" if unexpl else "Nothing left unexplained.")
    rows = [("bag", inp.get("bag", "(not recorded)")),
            ("line", _named(inp, "line")), ("train", _named(inp, "train")),
            ("data", inp.get("data", "-")),
            ("analysed", inp.get("date", "-"))]
    bag_name = Path(inp["bag"]).name if inp.get("bag") else ""
    figures = sorted(out.glob("*.svg"), key=lambda p: (
        _PLOT_ORDER.index(p.name) if p.name in _PLOT_ORDER else len(_PLOT_ORDER), p.name))
    evidence = [evidence_row(k, d) for k, d in ev.items()
                if not k.startswith("_") and isinstance(d, dict)]
    appendix = []
    for k, d in ev.items():
        if not k.startswith("_") and isinstance(d, dict) and d.get("details"):
            appendix.append({"id": f"details-{k}", "title": f"{k}: details of the fit",
                             "html": tree_of(d["details"])})
    for k, d in ev.items():
        if k.startswith("_") or not isinstance(d, dict):
            name = {"_model": "the believed model, the stages and the confirmation's checks"
                    }.get(k, k.strip("_"))
            appendix.append({"id": f"evidence-{k.strip('_')}", "title": name,
                             "html": tree_of(d)})
    for k, v in rep.items():
        if k not in _DIAGNOSE_SHOWN:
            appendix.append({"id": k, "title": k, "html": tree_of(v)})
    model = out / "model"
    if model.is_dir():
        for f in sorted(model.glob("*.yaml")):
            appendix.append({"id": f"model-{f.stem}", "title": f"model/{f.name} (the extended "
                             "model)", "html": f"<pre>{_e(f.read_text())}</pre>"})
    from markupsafe import Markup

    for a in appendix:
        a["html"] = Markup(a["html"])
    return {
        "title": f"diagnose: {cause}" + (f" in {bag_name}" if bag_name else ""),
        "header": {"rows": rows, "bag_name": bag_name},
        "verdict": {"cause": cause, "kind": "none" if cause == "none" else "found",
                    "sentence": sentence, "confirmed": blocks, "gain": gain, "left": left},
        "unexplained": [{"phase": u.get("phase", ""), "where": _span(u.get("where")),
                         "when": _span(u.get("when")), "speed": _span(u.get("speed")),
                         "size": unexplained_size(u), "reading": unexplained_line(u)}
                        for u in unexpl],
        "ranking": [{"cause": r.get("cause", ""), "score": html.unescape(sig4(r.get("score"))),
                     "status": r.get("status") or "", "params": params_text(r.get("parameters")),
                     "why": r.get("why") or ""} for r in ranking],
        "score_note": ("the BIC-penalised log-likelihood ratio against no cause, with the prior "
                       "odds of the causes tested; > 0: the data support the cause; none = 0"),
        "untestable": [u for u in rep.get("untestable") or [] if isinstance(u, dict)],
        "plots": [{"name": p.name, "uri": img_uri(p)} for p in figures],
        "evidence": evidence,
        "appendix": appendix,
    }


_EVIDENCE_KNOWN = ("score_alone", "loglik_gain", "n_params", "n", "parameters_alone",
                   "std_errors", "details", "accepted_at_stage")


def evidence_row(cause: str, d: dict) -> dict:
    """One cause's evidence as one row: its score alone, log-likelihood gain, parameter count,
    measurements, the fit alone (value +- standard error, unit) and the stage it was accepted
    at; other fields as "key = value"."""
    fit = d.get("parameters_alone") if isinstance(d.get("parameters_alone"), dict) else {}
    se = d.get("std_errors") if isinstance(d.get("std_errors"), dict) else {}
    parts = []
    for k, v in fit.items():
        unit = UNITS.get(k, "")
        unit = "" if unit in ("", "-") else f" {unit}"
        e = se.get(k)
        pm = f" +- {html.unescape(sig4(e))}" if isinstance(e, (int, float)) else ""
        if isinstance(v, list):
            parts.append(f"{k} = {with_unit(k, v)}")
        else:
            parts.append(f"{k} = {html.unescape(sig4(v))}{pm}{unit}")
    other = "; ".join(f"{k} = {_evidence_value(cause, k, v)}" for k, v in d.items()
                      if k not in _EVIDENCE_KNOWN)
    stage = d.get("accepted_at_stage")
    return {"cause": cause, "score": html.unescape(sig4(d.get("score_alone"))),
            "gain": html.unescape(sig4(d.get("loglik_gain"))),
            "k": html.unescape(sig4(d.get("n_params"))), "n": html.unescape(sig4(d.get("n"))),
            "fit": "; ".join(parts) or "-", "stage": "-" if stage is None else str(stage),
            "other": other}


def tree_of(v, depth: int = 0) -> str:
    """JSON data as nested lists of "key: value" (no table: a deep record stays as narrow as
    its text), numbers to 4 significant figures, short lists of scalars inline."""
    if isinstance(v, dict):
        if not v:
            return "&ndash;"
        items = []
        for k, x in v.items():
            if isinstance(x, (dict, list)) and not _flat(x):
                items.append(f"<li><b>{_e(k)}</b>:{tree_of(x, depth + 1)}</li>")
            else:
                items.append(f"<li><b>{_e(k)}</b>: {tree_of(x, depth + 1)}</li>")
        return f'<ul class="tree">{"".join(items)}</ul>'
    if isinstance(v, list):
        if _flat(v):
            return _inline(v) if v else "[]"
        return ('<ol class="tree">' + "".join(f"<li>{tree_of(x, depth + 1)}</li>" for x in v)
                + "</ol>")
    return _num(v)


def _flat(x) -> bool:
    """A list of scalars (or of short lists of scalars) prints on one line."""
    if isinstance(x, dict):
        return False
    return all(not isinstance(y, (dict, list)) or (isinstance(y, list) and len(y) <= 4 and all(
        not isinstance(z, (dict, list)) for z in y)) for y in x)


def _named(inp: dict, key: str) -> str:
    path, name = inp.get(key), inp.get(f"{key}_name")
    if not path:
        return "(not recorded)"
    return f"{name} ({path})" if name else str(path)


def _span(r) -> str:
    if not r:
        return "-"
    a, b = (html.unescape(sig4(float(x))) for x in r)
    return a if a == b else f"{a} to {b}"


def render_diagnose(out: Path) -> str:
    """report.html's text for a diagnose output directory."""
    ctx = diagnose_context(Path(out))
    return _env().get_template("diagnose_report.html.j2").render(**ctx)


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
    md = (out / "report.md").read_text()
    body = markdown_html(md, out, used)
    # the first paragraphs after the title are fleet's verdict: mark them as such
    body = body.replace("</h1>\n", '</h1>\n<div class="verdict" id="verdict">', 1)
    if 'id="verdict"' in body:
        i = body.find("<h2>")
        body = body[:i] + "</div>\n" + body[i:] if i >= 0 else body + "</div>"
    rest = [p for p in sorted(out.glob("*.png")) if p.name not in used]
    if rest:
        body += '\n<h2 id="plots">Plots</h2>' + "".join(_figure(p) for p in rest)
    m = re.search(r"^#\s+(.*)$", md, re.M)
    return _page(m.group(1).strip() if m else "Fleet report", body)


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


def main(argv=None) -> int:
    import argparse

    from train_estimation.tools.report_browser import CHROMIUM, screenshot

    p = argparse.ArgumentParser(prog="report_html", description=__doc__.splitlines()[0])
    p.add_argument("dir", help="an output directory of diagnose or fleet")
    p.add_argument("--screenshot", metavar="PNG",
                   help="also render report.html in headless Chromium into PNG")
    p.add_argument("--size", default="1280",
                   help="screenshot size: W (px, the whole page's height) or WxH (1280)")
    p.add_argument("--chromium", default=None, help=f"browser binary ({CHROMIUM})")
    args = p.parse_args(argv)
    try:
        page = write_report_html(args.dir)
        print(f"wrote {page}")
        if args.screenshot:
            parts = args.size.lower().split("x")
            w, h = int(parts[0]), (int(parts[1]) if len(parts) > 1 else None)
            print(f"wrote {screenshot(page, Path(args.screenshot), (w, h), args.chromium)}")
    except (OSError, ValueError, json.JSONDecodeError) as exc:
        print(f"report_html: {' '.join(str(exc).split())}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
