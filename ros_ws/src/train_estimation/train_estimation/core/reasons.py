"""One vocabulary of rejection reasons and input events (pure, no dependencies).

Every estimator core, the :class:`~train_estimation.core.online.runner.EstimatorRunner`, the
nodes' logs
and ``check_bag`` use these names, so that a count in a node's log, a counter of the runner and a
line of ``check_bag`` mean the same thing. A reason string is ``NAME`` or ``NAME: detail``; counts
are kept per ``NAME`` (:func:`category`).

Rejections refuse a reading (counted, the state untouched); accepted outcomes and events are
not rejections: an event is accepted input worth one log line (a sequence or clock reset).
"""

from __future__ import annotations

# -- rejections --------------------------------------------------------------------------------
NON_FINITE = "non_finite"  # NaN/inf in a stamp or a value
NON_POSITIVE_VARIANCE = "non_positive_variance"  # stated variance <= 0
OUT_OF_ORDER = "out_of_order"  # older than what the estimator has already fused (beyond history)
DUPLICATE = "duplicate"  # same sample again (same seq and stamp, or same stamp)
FUTURE_STAMP = "future_stamp"  # stamped far after its arrival / the other inputs (clock error)
STALE_STAMP = "stale_stamp"  # stamped far before its arrival (clock error, replayed message)
UNKNOWN_BALISE = "unknown_balise"  # balise id not in the line map
BALISE_MAP_MISMATCH = "balise_map_mismatch"  # sent position contradicts the map
OUTSIDE_GATE = "outside_gate"  # innovation beyond the gate (gross outlier)
UNKNOWN_KIND = "unknown_kind"  # not control, odometer or balise
INVALID = "invalid"  # malformed otherwise (wrong type or shape)
NUMERICAL_FAILURE = "numerical_failure"  # the update produced NaN: the old state is kept
ESTIMATOR_FAILED = "estimator_failed"  # the estimator raised an exception earlier: its state
#   is not trusted, nothing is fused, every reading's slot is an ALARM estimate

REJECTIONS = (NON_FINITE, NON_POSITIVE_VARIANCE, OUT_OF_ORDER, DUPLICATE, FUTURE_STAMP,
              STALE_STAMP, UNKNOWN_BALISE, BALISE_MAP_MISMATCH, OUTSIDE_GATE, UNKNOWN_KIND,
              INVALID, NUMERICAL_FAILURE, ESTIMATOR_FAILED)

# -- accepted outcomes (not rejections) ----------------------------------------------------------
OK = "ok"
MISSING = "missing"  # a lost odometer slot entered as alpha = 0 (Wen eq. (11))
IGNORED = "ignored"  # validated, not used by this estimator (FOH and balises)
ACCEPTED = (OK, MISSING, IGNORED)

# -- events: accepted input that changes how later input is read (logged once, counted) ----------
SEQ_RESET = "seq_reset"  # sequence number went back (sensor reboot, wrap-around)
CLOCK_RESET = "clock_reset"  # a stamp clock jumped and stayed: re-anchored
SEQ_SKIP = "seq_skip"  # the sample counter skipped (or repeated) samples, the clock ran on
LINK_LATENCY = "link_latency"  # the link's latency moved and stayed, the stamps ran on
COUNT_SLIP = "count_slip"  # the odometer's count left its speed (a wheel slip or slide), the
#   stamps stayed on their clock (no sample counter)
FUSED_LATE = "fused_late"  # arrived after later readings, fused by rewinding the history
OUTAGE = "outage"  # no odometer for longer than the outage threshold
RELOCATED = "relocated"  # two agreeing balises moved the odometer's count by more than it claimed
BALISE_EXCLUDED = "balise_excluded"  # a fused balise shown to lie by a later one, taken out
BALISE_LATENCY = "balise_latency"  # the balise reader found to stamp later than its prior allows
VARIANCE_UNSTATED = "variance_unstated"  # a stream whose variances are 0: not stated, believed used
COUNT_RESET = "count_reset"  # the odometer restarted its count (a reboot: its counter went back,
#   or without a counter two readings off the old count's course): its count spliced
COUNT_ORIGIN = "count_origin"  # the first count far from zero: origin widened until a balise
START_EXCLUDED = "start_excluded"  # the balises contradict the start: calibrated without it
COUNT_EXCLUDED = "count_excluded"  # a balise and the odometer's speeds contradict its count:
#   the count is no longer read (the estimator runs as with use_distance false)
SEQ_UNSTATED = "seq_unstated"  # a stream whose seq never moves: no counter, judged by stamps
STAMP_UNSTATED = "stamp_unstated"  # commands stamped 0: taken at their arrival (the contract's)
EVENTS = (SEQ_RESET, CLOCK_RESET, SEQ_SKIP, LINK_LATENCY, COUNT_SLIP, FUSED_LATE, OUTAGE,
          RELOCATED, BALISE_EXCLUDED, BALISE_LATENCY, VARIANCE_UNSTATED, COUNT_RESET, COUNT_ORIGIN,
          START_EXCLUDED, COUNT_EXCLUDED, SEQ_UNSTATED, STAMP_UNSTATED)

ALL = REJECTIONS + ACCEPTED + EVENTS

DESCRIPTION = {
    NON_FINITE: "NaN or infinite stamp or value",
    NON_POSITIVE_VARIANCE: "stated variance <= 0",
    OUT_OF_ORDER: "older than the history the estimator keeps",
    DUPLICATE: "same sample twice",
    FUTURE_STAMP: "stamp far after its arrival time (clock error)",
    STALE_STAMP: "stamp far before its arrival time (clock error)",
    UNKNOWN_BALISE: "balise id not in the line map",
    BALISE_MAP_MISMATCH: "balise position contradicts the line map",
    OUTSIDE_GATE: "innovation outside the gate (gross outlier)",
    UNKNOWN_KIND: "not control, odometer or balise",
    INVALID: "malformed reading",
    NUMERICAL_FAILURE: "update produced NaN; state kept",
    ESTIMATOR_FAILED: "the estimator failed earlier (an exception): ALARM, nothing fused",
    OK: "fused",
    MISSING: "lost odometer slot (alpha = 0)",
    IGNORED: "validated, not used",
    SEQ_RESET: "sequence number went back (reboot/wrap)",
    CLOCK_RESET: "stamp clock jumped; re-anchored",
    SEQ_SKIP: "sample counter skipped samples while the clock ran on; grid re-learnt",
    LINK_LATENCY: "the link's latency moved and stayed while the stamps ran on; no clock step",
    COUNT_SLIP: "the odometer's count (no sample counter) left its speed while the stamps and "
                "their arrivals stayed on their clock (a wheel slip or slide): no clock step, "
                "the count's clock restarts",
    FUSED_LATE: "arrived late, fused by rewinding",
    OUTAGE: "no odometer for longer than the outage threshold",
    RELOCATED: "odometer count moved onto two agreeing balises",
    BALISE_EXCLUDED: "a fused balise shown to lie by a later one, taken out of the count",
    BALISE_LATENCY: "the balise reader stamps later (or earlier) than balise_latency_std "
                    "allows: its latency is now calibrated with a wide prior",
    COUNT_RESET: "the odometer restarted its count (a reboot: its counter went back, or "
                 "without a counter two readings agreed off the old count's course), or may "
                 "have (without a counter, after a silence it could have rebooted in): spliced "
                 "onto the old one where the estimate was predicted, the origin's variance "
                 "grown by the prediction's",
    COUNT_ORIGIN: "the odometer's first count is far from zero (data from mid-run, or a count "
                  "from power-up): its origin is widened to cover it until a balise places it",
    START_EXCLUDED: "the balises contradict initial_position (their likelihood ratio against "
                    "the solution without a start passed the exclusion risk): the odometer's "
                    "count is calibrated from the balises alone",
    COUNT_EXCLUDED: "a balise the odometer's count contradicts agrees with the odometer's "
                    "speeds integrated from the last balise (their likelihood ratio against "
                    "a balise that lies passed the exclusion risk): the count is no longer "
                    "read, the speeds and the balises place the train (as use_distance false)",
    STAMP_UNSTATED: "commands stamped 0 (no stamp stated): their arrival time is used, the "
                    "reference clock the contract stamps commands on",
    SEQ_UNSTATED: "a stream's seq never moves (no sample counter): duplicates are stamps "
                  "already taken, lost samples counted from the stamps at the configured rate",
    VARIANCE_UNSTATED: "a stream states its variances as 0 (not stated): the believed train's "
                       "value (train.yaml) is used until it states one",
}


def category(reason: str) -> str:
    """The counted name of a reason string (``"NAME: detail"`` -> ``NAME``)."""
    return reason.split(":", 1)[0].strip()


def normalise(reason: str) -> str:
    """Map a free-text reason (e.g. of ``braking_filters``) onto this vocabulary, keeping detail.

    "" (accepted) stays "". Names of the vocabulary pass unchanged; known phrasings are mapped;
    anything else becomes ``invalid: <text>``: no rejection is counted without a vocabulary name.
    """
    if not reason:
        return ""
    cat = category(reason)
    if cat in ALL:
        return reason
    low = reason.lower()
    if low.startswith("numerical failure"):
        name = NUMERICAL_FAILURE
    elif "variance" in low and ("non-positive" in low or "non_positive" in low):
        name = NON_POSITIVE_VARIANCE
    elif "non-finite" in low or "non_finite" in low:
        name = NON_FINITE
    elif "out-of-order" in low or "duplicate" in low:
        name = OUT_OF_ORDER
    else:
        name = INVALID
    return f"{name}: {reason}"
