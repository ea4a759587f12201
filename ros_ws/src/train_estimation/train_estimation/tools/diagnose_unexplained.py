"""The ``unexplained`` entries of diagnose's report.json as a reader sees them: which kind an
entry is (a balise reading, the odometer's count, a step or a rate change of the train's clock,
the balise reader's latency, the odometer's or the balises' readings against their stated SD,
brakes that fade
as they heat, else a residual acceleration), its size with the unit of that kind, and its line
in the summary. The summary, the plots and report.html read entries through these functions.
"""

from __future__ import annotations

from train_estimation.core.offline.diagnose.confirm import UNDECIDED
from train_estimation.core.offline.diagnose.residuals import BALISE_WHY, SENSOR_WHY
from train_estimation.core.offline.diagnose.verdict import (
    DATUM_WHY,
    LATENCY_WHY,
    RATE_WHY,
    SCATTER_WHY,
)


def _span(r, unit: str) -> str | None:
    return None if r is None else f"{r[0]:.0f}-{r[1]:.0f} {unit}"


def at_balise(u: dict) -> bool:
    """An ``unexplained`` entry at one balise reading (``where`` one point): its size is the
    reading's offset in m, not an acceleration (docs/diagnose.md)."""
    w = u.get("where")
    return bool(w) and w[0] == w[1]


def clock_step(u: dict) -> bool:
    """An ``unexplained`` entry of a step of the train's clock (``when`` one point, no
    ``where``: no other entry has that shape): its size is the step in s (docs/diagnose.md)."""
    t = u.get("when")
    return not u.get("where") and bool(t) and t[0] == t[1]


def clock_rate(u: dict) -> bool:
    """An ``unexplained`` entry of a change of the train clock's rate (``when`` a span, no
    ``where``, the closest listed cause ``clock_drift`` with the rate's change as the reason:
    a time entry of the motion has the same shape): its size is what the clock reads more by
    the end, in s."""
    t, best = u.get("when"), u.get("best_listed") or {}
    return (not u.get("where") and bool(t) and t[0] != t[1]
            and best.get("cause") == "clock_drift"
            and str(best.get("why", "")).startswith(RATE_WHY))


def balise_latency(u: dict) -> bool:
    """An ``unexplained`` entry of a balise reader that stamps late (no ``where`` nor ``when``,
    the closest listed cause ``clock_drift`` with the latency as the reason): its size is the
    latency in s."""
    best = u.get("best_listed") or {}
    return (not u.get("where") and not u.get("when")
            and str(best.get("why", "")).startswith(LATENCY_WHY))


def datum_shift(u: dict) -> bool:
    """An ``unexplained`` entry of the map's gradients lying apart from the balises (no
    ``where`` nor ``when``, the reason beginning with ``DATUM_WHY``): its size is the shift in
    m (> 0: the gradients act further on than the balises place the run)."""
    best = u.get("best_listed") or {}
    return (not u.get("where") and not u.get("when")
            and str(best.get("why", "")).startswith(DATUM_WHY))


def sensor_noise(u: dict) -> bool:
    """An ``unexplained`` entry of odometer speed readings or balise readings that are not the
    sensor stated (no ``where`` nor ``when``, the reason beginning with ``SENSOR_WHY`` or
    ``BALISE_WHY``): its size is the readings' SD over the stated SD (docs/diagnose.md)."""
    best = u.get("best_listed") or {}
    return (not u.get("where") and not u.get("when")
            and str(best.get("why", "")).startswith((SENSOR_WHY, BALISE_WHY)))


def balise_scatter(u: dict) -> bool:
    """An ``unexplained`` entry of balise readings that scatter more than they state (no
    ``where`` nor ``when``, the reason beginning with ``SCATTER_WHY``): its size is their SD
    over the stated SD."""
    best = u.get("best_listed") or {}
    return (not u.get("where") and not u.get("when")
            and str(best.get("why", "")).startswith(SCATTER_WHY))


def heat_fade(u: dict) -> bool:
    """An ``unexplained`` entry of a braking weaker than believed that brakes fading as they
    heat explain better than the closest listed cause (phase braking, no ``where`` nor
    ``when``, the reason saying so): its size is the heat law's largest change of the
    acceleration in m/s^2 (> 0: less braking), not a residual."""
    best = u.get("best_listed") or {}
    return (u.get("phase") == "braking" and not u.get("where") and not u.get("when")
            and "a heat law fits better" in str(best.get("why", "")))


def undecided(u: dict) -> bool:
    """An ``unexplained`` entry of a low-adhesion section that a force fixed at its place fits
    as well, or of a downhill gradient that such a section fits as well (phase braking,
    ``where`` its stretch, the reason saying so): its size is the largest braking deficit
    there in m/s^2 (> 0: less braking), not a residual."""
    best = u.get("best_listed") or {}
    return (u.get("phase") == "braking" and bool(u.get("where"))
            and str(best.get("why", "")).startswith(UNDECIDED))


def on_odometer(u: dict) -> bool:
    """An ``unexplained`` entry of the odometer's count (``where`` and ``when`` both spans: no
    acceleration family gives both): its size is the odometer error in m (docs/diagnose.md)."""
    w, t = u.get("where"), u.get("when")
    return bool(w) and bool(t) and w[0] != w[1]


def unexplained_size(u: dict) -> str:
    """An ``unexplained`` entry's size with its unit, which depends on the entry's kind: an
    offset in m at a balise or on the odometer, a time in s for the clocks and the balise
    reader, a ratio to the stated SD for the odometer's readings, a residual acceleration in
    m/s^2 otherwise (docs/diagnose.md)."""
    size = u.get("size")
    if not isinstance(size, (int, float)):
        return "-"
    if on_odometer(u) or at_balise(u) or datum_shift(u):
        return f"{size:+.4g} m"
    if clock_step(u) or clock_rate(u) or balise_latency(u):
        return f"{size:+.4g} s"
    if sensor_noise(u) or balise_scatter(u):
        return f"x{size:.4g} of the stated SD"
    return f"{size:+.4g} m/s^2"


def unexplained_line(u: dict) -> str:
    """One line of the summary for an ``unexplained`` entry."""
    best = u.get("best_listed") or {}
    closest = f"; closest listed: {best['cause']} ({best['why']})" if best else ""
    if on_odometer(u):
        return (f"unexplained: the odometer counts differently on {_span(u['where'], 'm')} "
                f"({_span(u['when'], 's')}), {u['size']:+.1f} m from the train's position by "
                f"the end of it: it moved to other wheels or its calibration changed, not one "
                f"scale for the run" + closest)
    if datum_shift(u):
        return (f"unexplained: the map's gradients act {u['size']:+.1f} m from where the "
                f"balises place the run (two surveys on two datums), no listed cause" + closest)
    if clock_step(u):
        return (f"unexplained: the train's clock jumped by {u['size']:+.3f} s at "
                f"{u['when'][0]:.1f} s (the odometer's sample grid moved at once): the readings "
                f"after it are analysed on the clock before it" + closest)
    if clock_rate(u):
        return (f"unexplained: the train's clock changes its rate at {u['when'][0]:.0f} s and "
                f"reads {u['size']:+.3f} s more by {u['when'][1]:.0f} s than one rate says"
                + closest)
    if sensor_noise(u) or balise_scatter(u):
        return f"unexplained: {best['why']} (phase all, the whole run)"
    if heat_fade(u):
        sp = u["speed"]
        return (f"unexplained: the brakes deliver less than believed (up to {u['size']:+.3f} "
                f"m/s^2, braking at {sp[0]:.1f}-{sp[1]:.1f} m/s), as brakes that fade as they "
                f"heat: no listed cause; closest listed: {best['cause']} ({best['why']})")
    if undecided(u):
        sp = u.get("speed") or [0.0, 0.0]
        return (f"unexplained: braking on {_span(u['where'], 'm')} at {sp[0]:.1f}-{sp[1]:.1f} "
                f"m/s delivers up to {u['size']:+.3f} m/s^2 less than believed, a low-adhesion "
                f"section or a force fixed there: one run cannot tell; closest listed: "
                f"{best['cause']} ({best['why']})")
    if balise_latency(u):
        sp = u["speed"]
        side, who = (("behind", "the balise reader stamps late") if u["size"] >= 0 else
                     ("ahead of", "the balise reader stamps early, or the odometer's readings "
                                  "are older than their stamps"))
        return (f"unexplained: every balise reading lies {abs(u['size']):.3f} s x speed {side} "
                f"the train's position by the odometer (read at {sp[0]:.1f}-{sp[1]:.1f} m/s): "
                f"{who}, no listed cause" + closest)
    if at_balise(u):
        return (f"unexplained: the balise at {u['where'][0]:.0f} m (read at {u['when'][0]:.0f} s, "
                f"{u['speed'][0]:.1f} m/s) is {u['size']:+.1f} m from the train's position by "
                f"the odometer: it lies elsewhere than the map says, or another balise was read"
                + closest)
    where = [x for x in (_span(u.get("where"), "m"), _span(u.get("when"), "s")) if x]
    sp = u.get("speed")
    return (f"unexplained: {u['phase']}" + (f" on {', '.join(where)}" if where else "")
            + (f" at {sp[0]:.1f}-{sp[1]:.1f} m/s" if sp else "")
            + f", residual {u['size']:+.3f} m/s^2" + closest)
