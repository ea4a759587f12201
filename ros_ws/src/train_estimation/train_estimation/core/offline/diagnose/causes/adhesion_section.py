"""``adhesion_section``: braking weaker only on a stretch of track (wet rail, leaves): the
braking acceleration delivered is x ``factor`` while the train's reference point is on
[start, end) (train_core dynamics.py); traction is untouched.

Like a gradient section, a sum of position bins: per bin the believed braking there
(f0 a_br on the steps whose reference position is in the bin), and a section [i, j) of the bins
the run brakes in is (factor - 1) times their sum. Every section is scored at once by prefix sums
(``stage.best_section``, factor < 1 only) on one filter run over the bins
(``drive.Candidates``). A braking-rate
change acts on every brake application, a section only on those over it: a section covering
every braking bin is the braking rate by another name and scores below it (one parameter more).
"""

from __future__ import annotations

import weakref

import numpy as np
from train_core.effects import AdhesionSectionEffect
from train_core.model import G

from ..stage import best_section
from .base import Cause, resolved
from .braking_rate import brakes_while_moving
from .drive import Candidates

# The lowest adhesion coefficient a rail gives (leaf-covered, wet rail's worst is of this
# order): a brake asking for less than MU_MIN g is delivered whole on any rail, so adhesion
# cannot weaken it; a section that weakens only such brakings is a force of another kind.
MU_MIN = 0.02


class AdhesionSection(Cause):
    name = "adhesion_section"
    range_bound = True  # plausible() is a physical range: the factor, the braking asked for
    # the halves of its stretch (:meth:`halves_own`), not the held-out folds': each fold's fit
    # chooses its own stretch, so the two sizes are of two sections, not two estimates of one
    halves = ("factor",)
    half_quantity = ("factor", lambda c: 1.0 + c)

    def nominal(self, mo) -> dict:
        return {"factor": 1.0}

    def half_columns(self, fit, mo, others, cuts) -> tuple:
        """(Bv, Bs) (n_ev, 2): the braking of the model ``others`` (delayed by its brake delay,
        scaled by its mass change) on [cuts[0], cuts[1]) and on [cuts[1], cuts[2]), per unit
        of factor - 1."""
        Bv, Bs = braking_on(mo, cuts, cells=True, a_br=null_braking(mo, others))
        return others.drive_gain * Bv, others.drive_gain * Bs
    family = "motion"

    def untestable(self, run, cfg, own) -> str | None:
        return None if brakes_while_moving(run, cfg) else "no braking while moving in the data"

    def fit(self, st) -> tuple:
        mo = st.mo
        a_br = null_braking(mo, st.null)
        bins, drift = braking_bins(mo, a_br)
        if bins.size == 0:
            return st.null_ll(), 3, {}, {}, {}
        cand = Candidates(st, drift=drift)
        e0 = np.zeros(cand.k + 2)
        e0[0] = 1.0
        e1 = np.zeros(cand.k + 2)
        e1[1] = 1.0
        # weaker only (factor < 1): stronger braking on a stretch is not this cause
        quad, a, b, th, se = best_section(cand.W, e0, e1, np.arange(2, cand.k + 2), 1, sign=-1.0)
        if not np.isfinite(quad):
            return st.null_ll(), 3, {}, {}, {}
        i, j = int(bins[a]), int(bins[b - 1]) + 1
        quad, start, end, th, se = _refine(st, mo.bin_edges[i], mo.bin_edges[j], quad, th, se,
                                           a_br)
        return st.null_ll() + cand.dll(quad), 3, \
            {"start": start, "end": end, "factor": 1.0 + th}, {"factor": se}, \
            {"bins": (i, j)}

    # the braking weaker in proportion to the braking asked for at its place; a force fixed
    # there is a gradient the map lacks (downhill: braking seems weaker)
    fixed_rival = "a downhill gradient the map lacks (a force fixed at that place)"
    time_rival = "braking weaker while the train braked there (a brake fault of that moment)"
    global_rival = "braking_rate"
    # braking weaker at the end of each long braking (the brakes hot) is weaker there, on
    # whichever stretch the longest braking ends
    heat_rival = "brakes that fade as they heat"

    def resolution(self, fit, mo) -> str | None:
        """Braking on one stretch weaker by more than 3 SE and by 5 %: a few brake
        applications over a stretch scatter by a few per cent (driver, load, rail) without
        any low-adhesion section. And braked over for at least ``MIN_BRAKING_TIME``: a section
        the train brakes on for a fraction of a second is a kink in the speed that one or two
        readings make (a balise read off where the odometer puts the train), not a stretch
        of rail whose adhesion the data measure."""
        inside, _ = self.beyond(fit, mo)
        t_in = float(np.count_nonzero(inside)) * mo.grid.dt
        if t_in < MIN_BRAKING_TIME:
            return (f"below resolution: braked over the section for {t_in:.2f} s, less than "
                    f"{MIN_BRAKING_TIME:g} s")
        return resolved("factor", fit.parameters["factor"] - 1.0,
                        fit.std_errors.get("factor"), 0.05)

    def plausible(self, fit, mo) -> str | None:
        """Low adhesion weakens the braking a train gets, down to none: a factor at or below
        0 (a brake that drives the train on) is a force of another kind. And it limits only a
        braking that asks for more than the rail's adhesion gives: where every braking asked
        for on the stretch is below ``MU_MIN`` g, no rail limits it, and a deficit there is a
        force of another kind (a downhill gradient run in light braking)."""
        f = float(fit.parameters["factor"])
        if f <= 0.0:
            return (f"not a low-adhesion section: braking x {f:.2f} there (a brake that drives "
                    "the train is no adhesion loss)")
        if mo is None:
            return None
        inside, _ = self.beyond(fit, mo)
        if not inside.any():
            return None
        asked = float(np.max(-mo.f0 * mo.a_br0[inside]))
        if asked > MU_MIN * G:
            return None
        return (f"not a low-adhesion section: the braking asked for there is at most "
                f"{asked:.3f} m/s^2, which any rail gives (adhesion {asked / G:.4f}, the lowest "
                f"a rail has about {MU_MIN:g})")

    def beyond(self, fit, mo):
        """The section's braking factor on every brake application while moving."""
        p = fit.parameters
        brk = mo.f0 * mo.a_br0 * mo.moving
        inside = (brk < 0) & (mo.x_ref >= p["start"]) & (mo.x_ref < p["end"])
        return inside, (p["factor"] - 1.0) * brk

    def extend_null(self, null, fit, mo) -> None:
        # built by the stage at the null's braking timing (Null.brake_sections)
        p = fit.parameters
        null.brake_sections.append((float(p["start"]), float(p["end"]), float(p["factor"])))

    def effect(self, params: dict, duration: float) -> AdhesionSectionEffect:
        return AdhesionSectionEffect(float(params["start"]), float(params["end"]),
                                     float(params["factor"]))

    def model_effect(self, fit, ctx):
        """The section clipped to the line, the factor to what the effect's parser takes."""
        p = fit.parameters
        start, end = max(0.0, float(p["start"])), min(ctx.line_length, float(p["end"]))
        if end <= start:
            return None, (f"adhesion_section not in the model (section [{p['start']:.0f}, "
                          f"{p['end']:.0f}) m is outside the line)")
        factor = float(np.clip(p["factor"], 0.0, 2.0))
        return AdhesionSectionEffect(start, end, factor), (
            f"adhesion_section: braking x {factor:.3f} on [{start:.0f}, {end:.0f}) m")

    def series(self, params: dict, mo, out: dict) -> None:
        out["adhesion_section"] = (params["start"], params["end"], params["factor"])


# the section's ends are refined within one position bin either side, in this many steps per bin
EDGE_STEPS = 8
MIN_BRAKING_TIME = 1.0  # s of braking over a section that its factor needs (resolution)


def _refine(st, lo: float, hi: float, quad: float, th: float, se: float,
            a_br: np.ndarray | None = None) -> tuple:
    """The section [lo, hi) found on the position bins with its ends refined to 1/EDGE_STEPS of
    a bin (the world's section ends anywhere; a quarter bin of 47 % weaker braking left out at
    an end is a residual the gradient search then takes for a section of its own): cells of
    that width over a bin either side of each end (one cell between them where the ends are
    far apart), and the best contiguous run of cells (``stage.best_section``, weaker only).
    Returns (quad, start, end, theta, se); the binned section's where the refined one is not
    better. ``a_br``: the braking the cells scale (None: the believed ``mo.a_br0``)."""
    mo = st.mo
    w = float(mo.bin_edges[1] - mo.bin_edges[0]) if mo.bin_edges.size > 1 else 0.0
    if not w > 0.0:
        return quad, float(lo), float(hi), th, se
    fine = w / EDGE_STEPS
    if (hi - lo) <= 2 * w:
        cuts = np.arange(lo - w, hi + w + fine / 2, fine)
    else:
        cuts = np.concatenate([np.arange(lo - w, lo + w + fine / 2, fine),
                               np.arange(hi - w, hi + w + fine / 2, fine)])
    cand = Candidates(st, drift=braking_on(mo, cuts, cells=True, a_br=a_br))
    e0, e1 = np.zeros(cand.k + 2), np.zeros(cand.k + 2)
    e0[0], e1[1] = 1.0, 1.0
    q, a, b, t, s = best_section(cand.W, e0, e1, np.arange(2, cand.k + 2), 1, sign=-1.0)
    if not q < quad:
        return quad, float(lo), float(hi), th, se
    return q, float(cuts[a]), float(cuts[b]), t, s


def braking_on(mo, cuts: np.ndarray, cells: bool = False,
               a_br: np.ndarray | None = None) -> tuple:
    """The drift increments (Bv, Bs) of the braking f0 a_br (``a_br`` on the grid, None: the
    believed ``mo.a_br0``) on the grid steps whose mid position is in [cuts[0], cuts[-1]): one
    column (``cells`` False: two cuts, a section) or one per cell [cuts[k], cuts[k + 1])."""
    xm = 0.5 * (mo.x_ref[1:] + mo.x_ref[:-1])
    col = np.searchsorted(cuts, xm, side="right") - 1
    inside = (col >= 0) & (col < cuts.size - 1)
    if not cells:
        col = np.zeros_like(col)
    return _braking_columns(mo, np.where(inside, col, -1), cuts.size - 1 if cells else 1, a_br)


def braking_at(mo, timing: float) -> np.ndarray:
    """m/s^2 on the grid: the believed braking through the actuator with the commands re-timed
    by ``timing`` s (the braking columns' ``B<timing>`` plus the believed braking; cached)."""
    cache = _BRAKING.setdefault(mo, {})
    key = round(float(timing), 6)
    if key not in cache:
        cache[key] = mo.a_br0 if key == 0.0 else mo._part(key, "braking", key)
    return cache[key]


def null_braking(mo, null) -> np.ndarray:
    """The braking a section of the null scales: delayed by the accepted brake delay's extra.
    Not re-timed by the common command-time offset (a nuisance of the clocks, a few tenths of
    a second at most), as the braking rate's columns are not: with it, a section fitted at a
    greedy stage whose offset stood at its grid's edge (a traction delay not yet accepted)
    moved the search (a traction delay of 1.31 s fitted 1.22 +- 0.015 s for 1.26 +- 0.04)."""
    return braking_at(mo, null.brake_extra)


def section_increments(mo, null) -> tuple[np.ndarray, np.ndarray]:
    """(bv, bs), each (n_ev,): what the null's low-adhesion sections (``Null.brake_sections``)
    add to its drift: (factor - 1) times the braking at the null's timing on each stretch."""
    a_br = null_braking(mo, null)
    n = mo.ev.t.size
    bv, bs = np.zeros(n), np.zeros(n)
    for start, end, factor in null.brake_sections:
        cv, cs = braking_on(mo, np.array([start, end]), a_br=a_br)
        bv += (factor - 1.0) * cv[:, 0]
        bs += (factor - 1.0) * cs[:, 0]
    return bv, bs


_BRAKING: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()  # Motion -> {timing: a_br}


def _step_braking(mo, a_br: np.ndarray | None = None) -> np.ndarray:
    """m/s^2 per grid step: the braking f0 a_br while moving (step means; ``a_br`` None: the
    believed ``mo.a_br0``)."""
    a = mo.a_br0 if a_br is None else a_br
    return mo.f0 * 0.5 * (a[1:] + a[:-1]) * 0.5 * (mo.moving[1:] + mo.moving[:-1])


def _braking_columns(mo, col: np.ndarray, n: int, a_br: np.ndarray | None = None) -> tuple:
    """(Bv, Bs) (n_ev, ``n``): the braking f0 a_br of each grid step (``a_br`` None: the
    believed one) added to its column ``col`` (per grid step; < 0: in none)."""
    g, ev = mo.grid, mo.ev
    brk = _step_braking(mo, a_br)
    on = (brk < 0.0) & (col >= 0)
    Bv, Bs = np.zeros((ev.t.size, n)), np.zeros((ev.t.size, n))
    inc = brk[on] * g.dt
    np.add.at(Bv, (g.k[on], col[on]), inc)
    np.add.at(Bs, (g.k[on], col[on]), inc * g.lever[on])
    return Bv, Bs


def braking_bins(mo, a_br: np.ndarray | None = None) -> tuple[np.ndarray, tuple]:
    """The position bins (of the gradient search, ``mo.bin_edges``) the run brakes in and, per
    bin, the drift increments (Bv, Bs) (n_ev, n) of the braking f0 a_br there (``a_br`` None:
    the believed one)."""
    j = mo.step_bin
    bins = np.unique(j[_step_braking(mo, a_br) < 0.0])
    # steps outside these bins do not brake: _braking_columns leaves them out
    return bins, _braking_columns(mo, np.searchsorted(bins, j), bins.size, a_br)


CAUSE = AdhesionSection()
