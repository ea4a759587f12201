"""A small SVG plot writer for diagnose's figures (numpy and the standard library only).

A ``Figure`` of fixed pixel size holds a grid of ``Axes`` (stacked sharing x, or side by side
sharing y); each maps data to pixels and draws polylines (decimated to each pixel column's
minimum and maximum, so spikes stay visible), step lines, dots, filled bands, shaded spans,
bars, error bars, horizontal and vertical lines and text on a linear or log-10 y axis, with
"nice" ticks (1-2-5 steps), labels, light grid lines, a title and a legend box in a fixed
corner. Coordinates are written to 0.1 px; the same data give the same bytes.
"""

from __future__ import annotations

import math
from html import escape
from pathlib import Path

import numpy as np

PALETTE = {"C0": "#1f77b4", "C1": "#ff7f0e", "C2": "#2ca02c", "C3": "#d62728", "C4": "#9467bd",
           "k": "#000000", "tab:purple": "#9467bd"}  # matplotlib's, for the colours used
DASH = {"-": None, "--": "4,2", ":": "1,2"}
FONT = "font-family:DejaVu Sans,Arial,sans-serif"


def colour(c: str) -> str:
    """matplotlib's colour names these plots use ("C3", "k", grey "0.6") as #rrggbb."""
    if c in PALETTE or c.startswith("#"):
        return PALETTE.get(c, c)
    return "#" + f"{round(float(c) * 255):02x}" * 3


def _n(v: float) -> str:
    """A pixel coordinate to 0.1 px, without a trailing ".0" or a "-0"."""
    s = f"{v:.1f}".removesuffix(".0")
    return "0" if s == "-0" else s


def nice_ticks(lo: float, hi: float, target: int) -> np.ndarray:
    """Ticks on a 1-2-5 step inside [lo, hi]: about ``target`` of them, at least 3 when
    a smaller step gives them."""
    if not (math.isfinite(lo) and math.isfinite(hi)) or hi <= lo:
        return np.array([lo]) if math.isfinite(lo) else np.array([])
    raw = (hi - lo) / max(target, 1)
    mag = 10.0 ** math.floor(math.log10(raw))
    steps = [m * mag for m in (0.1, 0.2, 0.5, 1, 2, 5, 10)]
    i = next(j for j, st in enumerate(steps) if st >= raw * 0.999)
    while True:
        step = steps[i]
        k = np.arange(math.ceil(lo / step - 1e-9), math.floor(hi / step + 1e-9) + 1)
        if k.size >= 3 or i == 0:
            return k * step
        i -= 1


def tick_label(v: float, step: float) -> str:
    d = max(0, -math.floor(math.log10(step) + 1e-9)) if step > 0 else 0
    s = f"{v:.{d}f}"
    return s[1:] if s.startswith("-") and float(s) == 0 else s


class Axes:
    """One panel: its items in drawing order (dicts, inspectable), labels, limits, legend."""

    def __init__(self, box):
        self.box = box  # x, y, width, height in pixels
        self.items: list[dict] = []
        self.xlabel = self.ylabel = self.title = ""
        self.xlim = self.ylim = None
        self.logy = False
        self.legend_at = None  # "upper right", "upper left", ...
        self.legend_size = 8
        self.show_xticks = self.show_yticks = True

    def _add(self, kind, **kw):
        for k in ("x", "y", "lo", "hi", "h", "err"):
            if k in kw and kind != "hline":
                kw[k] = np.atleast_1d(np.asarray(kw[k], float))
        self.items.append(dict(kind=kind, **kw))

    def line(self, x, y, color="C0", lw=1.0, ls="-", alpha=1.0, label=None, marker=None, ms=3.0):
        self._add("line", x=x, y=y, color=color, lw=lw, ls=ls, alpha=alpha, label=label,
                  marker=marker, ms=ms)

    def step(self, x, y, **kw):
        """A step line through ``y`` at centres ``x`` (matplotlib's where="mid")."""
        self.line(*_mid_steps(x, y), **kw)

    def dots(self, x, y, color="0.5", alpha=0.3, label=None):
        self._add("dots", x=x, y=y, color=color, alpha=alpha, label=label)

    def band(self, x, lo, hi, color="C0", alpha=0.25, step=False, label=None):
        xs, lo, hi = (*_mid_steps(x, lo), _mid_steps(x, hi)[1]) if step else (x, lo, hi)
        self._add("band", x=xs, lo=lo, hi=hi, color=color, alpha=alpha, label=label)

    def hline(self, y, color="k", lw=0.6, ls="-", label=None):
        self._add("hline", y=float(y), color=color, lw=lw, ls=ls, label=label)

    def vlines(self, xs, color="0.6", lw=0.6, ls=":", label=None):
        self._add("vlines", x=xs, color=color, lw=lw, ls=ls, label=label)

    def vspan(self, a, b, color="C3", alpha=0.15, label=None):
        self._add("vspan", a=float(a), b=float(b), color=color, alpha=alpha, label=label)

    def bars(self, x, h, color="0.6", width=0.8, label=None):
        self._add("bars", x=x, h=h, color=color, width=width, label=label)

    def errorbar(self, x, y, err, color="C0", marker="o", ms=3.0, lw=1.0, label=None):
        self._add("errorbar", x=x, y=y, err=err, color=color, marker=marker, ms=ms, lw=lw,
                  label=label)

    def text(self, x, y, s, size=7):
        """``s`` hanging below (x, y), or below the panel's top edge when ``y`` is None."""
        self._add("text", x=x, y=math.nan if y is None else float(y), s=str(s), size=size)

    def legend(self, loc="upper right", size=8):
        self.legend_at, self.legend_size = loc, size

    def data_limits(self, axis: str):
        """The extent of the items' data along "x" or "y" (None when there is none)."""
        vals = []
        for it in self.items:
            k = it["kind"]
            if axis == "x":
                vals += [it["x"]] if "x" in it else [[it["a"], it["b"]]] if k == "vspan" else []
                vals += [it["x"] - it["width"] / 2, it["x"] + it["width"] / 2] if k == "bars" \
                    else []
            else:
                if k in ("line", "dots", "hline"):
                    vals.append(it["y"])
                elif k == "band":
                    vals += [it["lo"], it["hi"]]
                elif k == "bars":
                    vals.append(it["h"][it["h"] > 0] if self.logy else np.append(it["h"], 0))
                elif k == "errorbar":
                    vals += [it["y"] - it["err"], it["y"] + it["err"]]
        v = np.concatenate([np.ravel(a) for a in vals]) if vals else np.array([])
        v = v[np.isfinite(v)]
        if axis == "y" and self.logy:
            v = v[v > 0]
        return (float(v.min()), float(v.max())) if v.size else None


def _mid_steps(x, y):
    x, y = np.asarray(x, float), np.asarray(y, float)
    if x.size < 2:
        return x, y
    return np.concatenate([x[:1], np.repeat(0.5 * (x[1:] + x[:-1]), 2), x[-1:]]), np.repeat(y, 2)


def _padded(lim, log=False):
    lo, hi = lim
    if log:
        a, b = math.log10(lo), math.log10(hi)
        p = 0.05 * (b - a) if b > a else 0.5
        return 10 ** (a - p), 10 ** (b + p)
    p = 0.05 * (hi - lo) if hi > lo else (abs(lo) * 0.05 or 1.0)
    return lo - p, hi + p


def _decimate(px, py, width_cols):
    """Polyline vertices (finite, x ascending in runs) cut to the minimum and maximum of each
    pixel column when there are more than two per column."""
    if px.size <= 2 * width_cols:
        return px, py
    col = np.floor(px).astype(np.int64)
    starts = np.flatnonzero(np.concatenate([[True], col[1:] != col[:-1]]))
    lo, hi = np.minimum.reduceat(py, starts), np.maximum.reduceat(py, starts)
    last = py[np.append(starts[1:], px.size) - 1]
    up = np.abs(last - hi) <= np.abs(last - lo)  # the column ends high: its min first
    ys = np.column_stack([np.where(up, lo, hi), np.where(up, hi, lo)]).ravel()
    return np.repeat(px[starts], 2), ys


class Figure:
    """A figure of ``width`` x ``height`` inches at ``dpi`` with ``rows`` x ``cols`` panels."""

    def __init__(self, width, height, rows=1, cols=1, sharex=False, sharey=False,
                 height_ratios=None, top=0.4, dpi=90, space=0.2):
        self.w, self.h, self.dpi = round(width * dpi), round(height * dpi), dpi
        self.sharex, self.sharey, self.suptitle, self.axes = sharex, sharey, "", []
        left, right, bottom, gap, y = 0.95 * dpi, 0.2 * dpi, 0.6 * dpi, space * dpi, top * dpi
        ratios = np.asarray(height_ratios or [1] * rows, float)
        aw = (self.w - left - right - gap * (cols - 1)) / cols
        hs = (self.h - bottom - y - gap * (rows - 1)) * ratios / ratios.sum()
        for r in range(rows):
            for c in range(cols):
                ax = Axes((left + c * (aw + gap), y, aw, hs[r]))
                ax.show_xticks = not sharex or r == rows - 1
                ax.show_yticks = not sharey or c == 0
                self.axes.append(ax)
            y += hs[r] + gap

    def _limits(self):
        xl = [ax.data_limits("x") for ax in self.axes]
        yl = [ax.data_limits("y") for ax in self.axes]

        def union(ls):
            ls = [v for v in ls if v is not None]
            return (min(v[0] for v in ls), max(v[1] for v in ls)) if ls else (0.1, 1.0)

        for i, ax in enumerate(self.axes):
            if ax.xlim is None:
                ax.xlim = _padded(union(xl if self.sharex else [xl[i]]))
            if ax.ylim is None:
                ax.ylim = _padded(union(yl if self.sharey else [yl[i]]), ax.logy)
        if self.sharey:  # an explicit limit on one panel holds for all
            for ax in self.axes[1:]:
                ax.ylim, ax.logy = self.axes[0].ylim, self.axes[0].logy

    def svg(self) -> str:
        self._limits()
        out = [f'<svg xmlns="http://www.w3.org/2000/svg" width="{self.w}" height="{self.h}" '
               f'viewBox="0 0 {self.w} {self.h}" style="{FONT}">',
               f'<rect width="{self.w}" height="{self.h}" fill="#fff"/>']
        for i, ax in enumerate(self.axes):
            out += _Panel(ax, i).draw()
        if self.suptitle:
            out.append(_text(self.w / 2, 16, self.suptitle, 10, "middle"))
        out.append("</svg>")
        return "\n".join(out) + "\n"

    def save(self, path: Path) -> None:
        Path(path).write_text(self.svg(), encoding="utf-8")


def _text(x, y, s, size, anchor="start", extra=""):
    return (f'<text x="{_n(x)}" y="{_n(y)}" font-size="{size}" text-anchor="{anchor}"{extra}>'
            f"{escape(s)}</text>")


def _stroke(color, lw, ls="-", alpha=1.0):
    return (f'fill="none" stroke="{colour(color)}" stroke-width="{lw:g}"'
            + (f' stroke-dasharray="{DASH[ls]}"' if DASH.get(ls) else "")
            + (f' stroke-opacity="{alpha:g}"' if alpha < 1 else ""))


class _Panel:
    """The drawing of one Axes: data to pixels, then its SVG elements."""

    def __init__(self, ax: Axes, i: int):
        self.ax, self.clip = ax, f"p{i}"
        self.x0, self.y0, self.w, self.h = ax.box
        self.lx = ax.xlim
        self.ly = tuple(math.log10(v) for v in ax.ylim) if ax.logy else ax.ylim

    def X(self, x):
        lo, hi = self.lx
        return self.x0 + (np.asarray(x, float) - lo) / ((hi - lo) or 1.0) * self.w

    def Y(self, y):
        y = np.asarray(y, float)
        if self.ax.logy:
            with np.errstate(divide="ignore", invalid="ignore"):
                y = np.log10(np.where(y > 0, y, np.nan))
        lo, hi = self.ly
        return self.y0 + self.h - (y - lo) / ((hi - lo) or 1.0) * self.h

    def _path(self, px, py, attrs):
        ok = np.isfinite(px) & np.isfinite(py)
        parts, breaks = [], np.flatnonzero(np.diff(ok.astype(np.int8)))
        for seg in np.split(np.arange(px.size), breaks + 1):
            if seg.size < 1 or not ok[seg[0]]:
                continue
            sx, sy = px[seg], py[seg]
            if np.all(np.diff(sx) >= 0):
                sx, sy = _decimate(sx, sy, int(self.w) + 1)
            pts = " ".join(f"{_n(a)} {_n(b)}" for a, b in zip(sx, sy))
            parts.append(f"M{pts}" if sx.size > 1 else f"M{pts}h0")
        return f'<path d="{" ".join(parts)}" {attrs}/>' if parts else ""

    def _marks(self, px, py, it):
        """Markers "o" (circles) or "s" (squares) of ``it["ms"]`` points at (px, py)."""
        r, c, sq = it["ms"] / 2 * 1.25, colour(it["color"]), it.get("marker") == "s"
        return [f'<rect x="{_n(a - r)}" y="{_n(b - r)}" width="{_n(2 * r)}" height="{_n(2 * r)}"'
                f' fill="{c}"/>' if sq else f'<circle cx="{_n(a)}" cy="{_n(b)}" r="{_n(r)}" '
                f'fill="{c}"/>' for a, b in zip(px, py) if math.isfinite(a + b)]

    def _item(self, it):
        k, top, bot = it["kind"], self.y0, self.y0 + self.h
        if k == "line":
            px, py = self.X(it["x"]), self.Y(it["y"])
            el = [self._path(px, py, _stroke(it["color"], it["lw"], it["ls"], it["alpha"]))]
            return el + (self._marks(px, py, it) if it["marker"] else [])
        if k == "dots":  # one dot a pixel at most
            px, py = self.X(it["x"]), self.Y(it["y"])
            ok = np.isfinite(px) & np.isfinite(py)
            key = np.unique(np.round(py[ok]).astype(np.int64) * 100000
                            + np.round(px[ok]).astype(np.int64))
            d = "".join(f"M{k % 100000} {k // 100000}h0" for k in key)
            return [f'<path d="{d}" stroke="{colour(it["color"])}" stroke-width="1.6" '
                    f'stroke-linecap="round" stroke-opacity="{min(1.0, 2.5 * it["alpha"]):g}"/>']
        if k == "band":
            px, lo, hi = self.X(it["x"]), self.Y(it["lo"]), self.Y(it["hi"])
            ok = np.isfinite(px) & np.isfinite(lo) & np.isfinite(hi)
            px, lo, hi = px[ok], lo[ok], hi[ok]
            pts = np.concatenate([np.column_stack([px, hi]), np.column_stack([px, lo])[::-1]])
            d = "M" + " ".join(f"{_n(a)},{_n(b)}" for a, b in pts) + "Z"
            return [f'<path d="{d}" fill="{colour(it["color"])}" '
                    f'fill-opacity="{it["alpha"]:g}"/>'] if px.size else []
        if k == "hline":
            y = float(self.Y(it["y"])[()])
            return [f'<path d="M{_n(self.x0)} {_n(y)}H{_n(self.x0 + self.w)}" '
                    f'{_stroke(it["color"], it["lw"], it["ls"])}/>'] if math.isfinite(y) else []
        if k == "vlines":
            d = "".join(f"M{_n(x)} {_n(top)}V{_n(bot)}" for x in self.X(it["x"]))
            return [f'<path d="{d}" {_stroke(it["color"], it["lw"], it["ls"])}/>']
        if k == "vspan":
            a, b = sorted(float(v) for v in self.X([it["a"], it["b"]]))
            return [f'<rect x="{_n(a)}" y="{_n(top)}" width="{_n(b - a)}" height="{_n(bot - top)}"'
                    f' fill="{colour(it["color"])}" fill-opacity="{it["alpha"]:g}"/>']
        if k == "bars":
            base = bot if self.ax.logy else float(self.Y(0.0)[()])
            a, b = self.X(it["x"] - it["width"] / 2), self.X(it["x"] + it["width"] / 2)
            return [f'<rect x="{_n(a)}" y="{_n(min(y, base))}" width="{_n(b - a)}" '
                    f'height="{_n(abs(base - y))}" fill="{colour(it["color"])}"/>'
                    for a, b, y, h in zip(a, b, self.Y(it["h"]), it["h"])
                    if math.isfinite(y) and h != 0]
        if k == "errorbar":
            px, py = self.X(it["x"]), self.Y(it["y"])
            lo, hi = self.Y(it["y"] - it["err"]), self.Y(it["y"] + it["err"])
            ok = np.isfinite(px) & np.isfinite(lo) & np.isfinite(hi)
            d = "".join(f"M{_n(a)} {_n(b)}V{_n(c)}" for a, b, c in zip(px[ok], lo[ok], hi[ok]))
            return ([f'<path d="{d}" {_stroke(it["color"], it["lw"])}/>'] if d else []) + [
                self._path(px, py, _stroke(it["color"], it["lw"]))] + self._marks(px, py, it)
        if k == "text":
            x, y = float(self.X(it["x"])[0]), float(self.Y(it["y"])[0])
            y = top + 2 if math.isnan(it["y"][0]) else y
            return [_text(x, y + it["size"], it["s"], it["size"])] if math.isfinite(x + y) else []
        raise ValueError(f"unknown plot item {k}")

    def _ticks(self):
        ax, out, x0, y0, w, h = self.ax, [], self.x0, self.y0, self.w, self.h
        grid = 'stroke="#b0b0b0" stroke-width="0.8" stroke-opacity="0.3"'
        xt = nice_ticks(*self.lx, max(2, int(w // 75)))
        xs = [(float(self.X(v)), v) for v in xt]
        step = float(xt[1] - xt[0]) if xt.size > 1 else 1.0
        if ax.logy:
            dec = np.arange(math.ceil(self.ly[0] - 1e-9), math.floor(self.ly[1] + 1e-9) + 1)
            ys = [(float(self.Y(10.0 ** d)), f"{10.0 ** d:g}") for d in dec]
        else:
            yt = nice_ticks(*ax.ylim, max(2, int(h // 45)))
            ystep = float(yt[1] - yt[0]) if yt.size > 1 else 1.0
            ys = [(float(self.Y(v)), tick_label(v, ystep)) for v in yt]
        d = "".join(f"M{_n(px)} {_n(y0)}V{_n(y0 + h)}" for px, _ in xs)
        d += "".join(f"M{_n(x0)} {_n(py)}H{_n(x0 + w)}" for py, _ in ys)
        out.append(f'<path d="{d}" {grid}/>')
        ticks = "".join(f"M{_n(px)} {_n(y0 + h)}v3.5" for px, _ in xs)
        ticks += "".join(f"M{_n(x0)} {_n(py)}h-3.5" for py, _ in ys)
        out.append(f'<path d="{ticks}" stroke="#000" stroke-width="0.8"/>')
        if ax.show_xticks:
            out += [_text(px, y0 + h + 14, tick_label(v, step), 9, "middle") for px, v in xs]
        if ax.show_yticks:
            out += [_text(x0 - 6, py + 3, s, 9, "end") for py, s in ys]
        return out

    def _legend(self):
        ax = self.ax
        ents = [it for it in ax.items if it.get("label")]
        if not ax.legend_at or not ents:
            return []
        fs = ax.legend_size
        lh, bw = fs * 1.45, 0.58 * fs * max(len(e["label"]) for e in ents) + 34
        bh = lh * len(ents) + 6
        right, upper = "right" in ax.legend_at, "upper" in ax.legend_at
        bx = self.x0 + self.w - bw - 6 if right else self.x0 + 6
        by = self.y0 + 6 if upper else self.y0 + self.h - bh - 6
        out = [f'<rect x="{_n(bx)}" y="{_n(by)}" width="{_n(bw)}" height="{_n(bh)}" '
               'fill="#fff" fill-opacity="0.8" stroke="#ccc" stroke-width="0.8" rx="2"/>']
        for j, e in enumerate(ents):
            cy, c = by + 3 + lh * (j + 0.5), colour(e["color"])
            if e["kind"] in ("vspan", "bars", "band", "dots"):
                op = e.get("alpha", 1.0) if e["kind"] != "dots" else 1.0
                out.append(f'<rect x="{_n(bx + 6)}" y="{_n(cy - 4)}" width="20" height="8" '
                           f'fill="{c}" fill-opacity="{max(op, 0.3):g}"/>')
            else:
                out.append(f'<path d="M{_n(bx + 6)} {_n(cy)}h20" '
                           f'{_stroke(e["color"], max(e.get("lw", 1.0), 1.0), e.get("ls", "-"))}/>')
                if e.get("marker"):
                    out += self._marks([bx + 16], [cy], e)
            out.append(_text(bx + 30, cy + fs * 0.35, e["label"], fs))
        return out

    def draw(self) -> list[str]:
        ax, x0, y0, w, h = self.ax, self.x0, self.y0, self.w, self.h
        out = [f'<clipPath id="{self.clip}"><rect x="{_n(x0)}" y="{_n(y0)}" width="{_n(w)}" '
               f'height="{_n(h)}"/></clipPath>'] + self._ticks()
        out.append(f'<g clip-path="url(#{self.clip})">')
        out += [e for it in ax.items for e in self._item(it) if e] + ["</g>"]
        out.append(f'<rect x="{_n(x0)}" y="{_n(y0)}" width="{_n(w)}" height="{_n(h)}" '
                   'fill="none" stroke="#000" stroke-width="0.8"/>')
        if ax.xlabel and ax.show_xticks:
            out.append(_text(x0 + w / 2, y0 + h + 32, ax.xlabel, 10, "middle"))
        if ax.ylabel:
            cx, cy = x0 - 58, y0 + h / 2
            out.append(_text(cx, cy, ax.ylabel, 10, "middle",
                             f' transform="rotate(-90 {_n(cx)} {_n(cy)})"'))
        if ax.title:
            out.append(_text(x0 + w / 2, y0 - 6, ax.title, 11, "middle"))
        return out + self._legend()
