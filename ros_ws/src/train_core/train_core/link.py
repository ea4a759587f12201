"""Per-message radio link between the train and the wayside: which messages arrive.

Two models, both seeded through an explicit ``np.random.Generator``:

* ``bernoulli`` (Wen et al. 2017, eq. (11)-(12)): every message is received independently with

      Prob{alpha(k) = 1} = sum_{j=0}^{r-1} p^j (1 - p) = 1 - p^r,

  for frame error rate ``p`` and at most ``r`` transmissions (CSMA/CA with ARQ). Wen's example,
  p = 0.5 and r = 3, gives 0.875.

* ``gilbert_elliott``: a two-state Markov chain (good G, bad B) advanced once per message --
  or, given the link's time ``slot`` (the radio's cycle, s), once per slot elapsed: a topic that
  sends rarely (balises, every few hundred metres) then meets the channel's state at its own
  instants (n-step transition) instead of a burst lasting n of its own messages.
  Message k is lost with probability ``loss_good`` in G and ``loss_bad`` in B, then the state moves
  G -> B with ``p_good_bad`` and B -> G with ``p_bad_good``. With loss_good = 0 and loss_bad = 1
  the lengths of loss bursts are geometric on {1, 2, ...} with mean 1 / p_bad_good, and the
  stationary received fraction is p_bad_good / (p_good_bad + p_bad_good). The first message's
  state is drawn from the stationary distribution, so the process is stationary from the start.

One :class:`Link` per topic (odometer, balise), each with its own generator, so that a change in
one topic's traffic never shifts another topic's random stream.

Besides losses a link has:

* **latency**: a received message arrives ``latency + jitter * E`` seconds after it was sent,
  E ~ Exp(1) drawn per message from a *separate* generator (so switching latency on never changes
  which messages are lost). With jitter larger than the sample period, messages overtake each
  other: the receiver sees them out of order, as over a real radio.
* **outages** (a tunnel): no message of the topic is received while the train is inside one of
  the windows [t0, t1) (true time, s). The loss draw is still made, so the rest of the run's
  losses do not shift.

Pure module: numpy only.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

MODELS = ("bernoulli", "gilbert_elliott")


def bernoulli_received_probability(p: float, r: int) -> float:
    """Wen et al. (2017) eq. (12): sum_{j=0}^{r-1} p^j (1 - p), which telescopes to 1 - p^r."""
    return float(sum(p**j * (1.0 - p) for j in range(r)))


@dataclass(frozen=True)
class LinkParams:
    """Radio link model of one scenario (applies per message, per topic)."""

    model: str = "bernoulli"  # "bernoulli" or "gilbert_elliott"
    p: float = 0.5  # -, frame error rate per transmission (bernoulli)
    r: int = 3  # -, maximum number of transmissions per message (bernoulli)
    p_good_bad: float = 0.0  # -, per-message probability G -> B (gilbert_elliott)
    p_bad_good: float = 1.0  # -, per-message probability B -> G (gilbert_elliott)
    loss_good: float = 0.0  # -, probability a message is lost in the good state
    loss_bad: float = 1.0  # -, probability a message is lost in the bad state
    latency: float = 0.0  # s, fixed part of the transmission delay of a received message
    jitter: float = 0.0  # s, mean of the exponential random part of the delay
    outages: tuple[tuple[float, float], ...] = ()  # s, [t0, t1) windows with nothing received

    def in_outage(self, t: float) -> bool:
        return any(t0 <= t < t1 for t0, t1 in self.outages)

    @property
    def received_probability(self) -> float:
        """Long-run fraction of messages received (stationary for Gilbert-Elliott)."""
        if self.model == "bernoulli":
            return bernoulli_received_probability(self.p, self.r)
        pi_bad = self.stationary_bad
        return (1.0 - pi_bad) * (1.0 - self.loss_good) + pi_bad * (1.0 - self.loss_bad)

    @property
    def stationary_bad(self) -> float:
        """Stationary probability of the bad state: p_gb / (p_gb + p_bg)."""
        s = self.p_good_bad + self.p_bad_good
        return 0.0 if s == 0.0 else self.p_good_bad / s


class Link:
    """One topic's lossy link. ``transmit()`` returns True when the message arrives."""

    def __init__(self, params: LinkParams, rng: np.random.Generator,
                 delay_rng: np.random.Generator | None = None, slot: float | None = None):
        if params.model not in MODELS:
            raise ValueError(f"unknown link model {params.model!r} (allowed: {', '.join(MODELS)})")
        self.params = params
        self.rng = rng
        self.delay_rng = delay_rng if delay_rng is not None else np.random.default_rng(0)
        self.sent = 0
        self.dropped = 0
        self._p_recv = params.received_probability
        # Stationary start for the Markov chain (one uniform draw, also for bernoulli, so both
        # models consume the stream the same way).
        u0 = float(rng.random())
        self.bad = params.model == "gilbert_elliott" and u0 < params.stationary_bad
        self.slot = slot  # s, one chain step (None: one step per message)
        self._t_last: float | None = None

    def transmit(self) -> bool:
        """Decide one message's fate (one uniform draw; Gilbert-Elliott: two)."""
        p = self.params
        self.sent += 1
        if p.model == "bernoulli":
            ok = float(self.rng.random()) < self._p_recv
        else:
            u_loss, u_move = self.rng.random(2)
            ok = u_loss >= (p.loss_bad if self.bad else p.loss_good)
            # Advance the chain after the message (state k -> k + 1).
            self.bad = (u_move >= p.p_bad_good) if self.bad else (u_move < p.p_good_bad)
        if not ok:
            self.dropped += 1
        return bool(ok)

    def _advance(self, m: int) -> None:
        """m more chain steps at once: P(bad) = pi + (1{bad} - pi) lambda^m, with lambda =
        1 - p_good_bad - p_bad_good the chain's second eigenvalue and pi its stationary P(bad)
        (one uniform draw)."""
        p = self.params
        pi = p.stationary_bad
        lam = 1.0 - p.p_good_bad - p.p_bad_good
        p_bad = pi + ((1.0 if self.bad else 0.0) - pi) * lam ** m
        self.bad = float(self.rng.random()) < p_bad

    def send(self, t: float) -> float | None:
        """A message sent at true time ``t``: its arrival time, or None when it is lost."""
        if self.slot and self.params.model == "gilbert_elliott" and self._t_last is not None:
            n = int(round((t - self._t_last) / self.slot))
            if n > 1:  # the chain already took one step after the previous message
                self._advance(n - 1)
        self._t_last = t
        ok = self.transmit()
        if self.params.outages and self.params.in_outage(t):
            if ok:
                self.dropped += 1
            return None
        if not ok:
            return None
        p = self.params
        if p.jitter > 0.0:
            return t + p.latency + p.jitter * float(self.delay_rng.standard_exponential())
        return t + p.latency

    def transmit_many(self, n: int) -> np.ndarray:
        """Fates of ``n`` consecutive messages (bool array); same stream as n calls to transmit."""
        if self.params.model == "bernoulli":
            ok = self.rng.random(n) < self._p_recv
            self.sent += n
            self.dropped += int(n - ok.sum())
            return ok
        return np.fromiter((self.transmit() for _ in range(n)), dtype=bool, count=n)


def burst_lengths(received: np.ndarray) -> np.ndarray:
    """Lengths of the runs of consecutive lost messages in a boolean ``received`` sequence."""
    lost = np.concatenate(([False], ~np.asarray(received, dtype=bool), [False])).astype(np.int8)
    d = np.diff(lost)
    starts, ends = np.flatnonzero(d == 1), np.flatnonzero(d == -1)
    return ends - starts
