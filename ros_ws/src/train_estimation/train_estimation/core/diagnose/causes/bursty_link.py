"""``bursty_link``: odometer losses come in bursts (a two-state link) rather than independently.

A likelihood of its own on the gaps in ``seq``: Bernoulli (one loss probability) against a
two-state Markov chain on received/lost (Gilbert-Elliott with loss_good = 0, loss_bad = 1, whose
state is then observed). p_good_bad = P(lost | previous received), p_bad_good = P(received |
previous lost), per odometer sample."""

from __future__ import annotations

import math

import numpy as np
from train_core.effects import BurstyLinkEffect

from .base import Cause, resolved


class BurstyLink(Cause):
    name = "bursty_link"
    family = "link"

    def untestable(self, run, cfg, own) -> str | None:
        return own.get("untestable") if own else None

    def own_test(self, run) -> dict:
        return link_test(run)

    def resolution(self, fit, mo) -> str | None:
        """Bursts are bursts when the chain remembers its state: 1 - p_good_bad - p_bad_good
        (0 for independent losses) above 0.1."""
        p = fit.parameters
        if "p_good_bad" not in p or "p_bad_good" not in p:
            return "below resolution: no chain fitted"
        return resolved("state memory 1 - p_good_bad - p_bad_good",
                        1.0 - p["p_good_bad"] - p["p_bad_good"], None, 0.1)

    def extend_null(self, null, fit, mo) -> None:
        """Which messages arrive is not part of the motion model: nothing to add."""

    def effect(self, params: dict, duration: float) -> BurstyLinkEffect:
        return BurstyLinkEffect(float(params["p_good_bad"]),
                                float(max(params["p_bad_good"], 1e-6)))

    def gain(self, fit, ctx) -> dict:
        return ctx.own[self.name].get("gain") or {"metric": "held-out log-likelihood",
                                                  "before": None, "after": None}

    def own_series(self, own: dict, out: dict) -> None:
        """The loss runs, the loss fraction and the chain's p_bad_good (plotted whether the
        cause is accepted or not)."""
        if "loss_runs" in own:
            out["loss_runs"] = own["loss_runs"]
            out["loss_fraction"] = own.get("loss_fraction")
            out["loss_p_bad_good"] = own["parameters"].get("p_bad_good")


def link_test(run) -> dict:
    seq = run.odo_seq
    seq = np.unique(seq)
    n = int(seq[-1] - seq[0] + 1) if seq.size else 0
    if n < 20 or n > 50 * seq.size:
        return {"dll": 0.0, "k": 1, "n": max(n, 1), "parameters": {}, "untestable":
                "too few odometer samples or sequence numbers that jump (sensor resets)"}
    recv = np.zeros(n, dtype=bool)
    recv[seq - seq[0]] = True
    return markov_vs_bernoulli(recv)


def _xlogy(a, b):
    return a * math.log(b) if a > 0 else 0.0


def markov_vs_bernoulli(recv: np.ndarray) -> dict:
    """The two likelihoods of the received/lost sequence, the chain's parameters and the
    held-out gain (fit on the first half, log-likelihood per sample on the second)."""
    recv = np.asarray(recv, dtype=bool)
    n = recv.size
    lost = int((~recv).sum())
    p = lost / n
    ll0 = _xlogy(lost, p) + _xlogy(n - lost, 1 - p)
    prev, nxt = recv[:-1], recv[1:]
    n_rl = int((prev & ~nxt).sum())
    n_rr = int((prev & nxt).sum())
    n_lr = int((~prev & nxt).sum())
    n_ll = int((~prev & ~nxt).sum())
    p_gb = n_rl / max(n_rr + n_rl, 1)
    p_bg = n_lr / max(n_lr + n_ll, 1)
    first = _xlogy(1, p) if not recv[0] else _xlogy(1, 1 - p)
    ll1 = (first + _xlogy(n_rl, p_gb) + _xlogy(n_rr, 1 - p_gb) + _xlogy(n_lr, p_bg)
           + _xlogy(n_ll, 1 - p_bg))
    se = {"p_good_bad": math.sqrt(max(p_gb * (1 - p_gb), 1e-12) / max(n_rr + n_rl, 1)),
          "p_bad_good": math.sqrt(max(p_bg * (1 - p_bg), 1e-12) / max(n_lr + n_ll, 1))}
    out = {"dll": ll1 - ll0, "k": 1, "n": n,
           "parameters": {"p_good_bad": p_gb, "p_bad_good": max(p_bg, 1e-6)},
           "std_errors": se, "loss_fraction": p, "loss_runs": _runs(~recv)}
    h = n // 2
    if h > 20:
        out["gain"] = _held_out(recv[:h], recv[h:])
    return out


def _held_out(a: np.ndarray, b: np.ndarray) -> dict:
    pa = max(min(float((~a).sum()) / a.size, 1 - 1e-6), 1e-6)
    pa_rl = (a[:-1] & ~a[1:]).sum() / max(a[:-1].sum(), 1)
    pa_lr = (~a[:-1] & a[1:]).sum() / max((~a[:-1]).sum(), 1)
    pa_rl = min(max(pa_rl, 1e-6), 1 - 1e-6)
    pa_lr = min(max(pa_lr, 1e-6), 1 - 1e-6)
    before = float(np.mean(np.where(b, math.log(1 - pa), math.log(pa))))
    pb, nb = b[:-1], b[1:]
    lp = np.where(pb, np.where(nb, math.log(1 - pa_rl), math.log(pa_rl)),
                  np.where(nb, math.log(pa_lr), math.log(1 - pa_lr)))
    return {"metric": "held-out log-likelihood per odometer sample (second half, fitted on the "
                      "first)", "before": before, "after": float(np.mean(lp))}


def _runs(mask: np.ndarray) -> np.ndarray:
    m = np.concatenate([[False], mask, [False]]).astype(np.int8)
    d = np.diff(m)
    return np.flatnonzero(d == -1) - np.flatnonzero(d == 1)


CAUSE = BurstyLink()
