"""The train clock's step watch (core/numerics/clocks.StepWatch), driven directly as the
runner drives it: each answer acted on before the next is asked for."""

import math

import numpy as np
import pytest

from train_estimation.core.numerics.clocks import (
    ADMIT,
    HOLD,
    PASS,
    REFUSE,
    SKIP,
    STEP,
    TOL,
    StepWatch,
)

PERIOD, LATENCY = 0.1, 0.05


def silent_after(lost: int, got: int, risk: float = 1e-7) -> int:
    """The readings a step needs by the stated rule (clocks.silence_risk), computed here as the
    Beta function ratio B(lost + n + 1, got + n + 1) / B(lost + 1, got + n + 1) in logs."""
    for n in range(1, 1000):
        a, b = lost + 1, got + n + 1
        log_bf = (math.lgamma(a + n) + math.lgamma(a + b) - math.lgamma(a)
                  - math.lgamma(a + b + n))
        if log_bf <= math.log(risk):
            return n
    raise AssertionError("no n")


class Feed:
    """A 10 Hz odometer through a StepWatch; admission reduced to what the watch sees (the
    reading's offset votes for the train clock, the watch is told)."""

    def __init__(self, period=PERIOD):
        self.period = period
        self.w = StepWatch(period)
        self.admitted: list = []

    def admit(self, stamp, arrival):
        self.w.clock.add(stamp - arrival, arrival)
        self.w.admitted("odometer", stamp, arrival)
        self.admitted.append(stamp)

    def push(self, raw, arrival):
        """The actions for one reading stamped ``raw`` (as sent), acted on in turn."""
        stamp = self.w.onto_timeline(raw, odometer=True)
        if self.w.last is None:
            self.admit(stamp, arrival)
            return [(PASS, stamp)]
        acts = []
        for act in self.w.watch("odometer", stamp, {}, arrival, arrival):
            acts.append(act)
            if act[0] == ADMIT:
                self.admit(act[1][1], act[1][4])
            elif act[0] == PASS:
                self.admit(act[1], arrival)
        return acts

    def run_on(self, k0, k1, epoch=1000.0):
        for k in range(k0, k1):
            t = epoch + k * self.period
            assert self.push(t, t + LATENCY)[-1][0] == PASS


def test_a_backward_step_is_decided_after_min_judged_readings():
    f = Feed()
    f.run_on(0, 40)
    step = -3.0
    answers = []
    for k in range(40, 40 + f.w.min_judged):
        raw = 1000.0 + k * PERIOD + step
        answers.append(f.push(raw, 1000.0 + k * PERIOD + LATENCY))
    # held, each of the first min_judged - 1 (the integrity monitor is told they are)
    assert all(a == [(HOLD,)] for a in answers[:-1])
    acts = answers[-1]
    # measured from the arrivals: the readings' median offset less the clock's centre
    assert acts[0][0] == STEP and acts[0][1] == pytest.approx(step, abs=1e-9) and acts[0][3]
    assert f.w.shift == pytest.approx(step, abs=1e-9)
    # the held readings admitted on the old timeline, then this one: no gap, no repeat
    assert [a[0] for a in acts[1:]] == [ADMIT] * (f.w.min_judged - 1) + [PASS]
    assert f.admitted[-f.w.min_judged:] == pytest.approx(
        [1000.0 + k * PERIOD for k in range(40, 40 + f.w.min_judged)], abs=1e-9)
    assert not f.w.held
    # later readings are mapped back; their estimates are published at the stamps as sent
    raw = 1000.0 + 49 * PERIOD + step
    assert f.push(raw, 1000.0 + 49 * PERIOD + LATENCY) == [(PASS, pytest.approx(raw - step))]
    assert f.w.as_sent(f.admitted[-1]) == raw


def test_one_wrong_stamp_is_refused_not_taken_for_a_step():
    f = Feed()
    f.run_on(0, 40)
    bad = 1000.0 + 40 * PERIOD + 60.0  # a flipped bit: one reading 60 s ahead
    assert f.push(bad, 1000.0 + 40 * PERIOD + LATENCY) == [(HOLD,)]
    n, doubt, _ = f.w.doubt()
    assert n == 1 and doubt == pytest.approx(60.0, abs=1e-6)  # beyond the elapsed arrival time
    acts = f.push(1000.0 + 41 * PERIOD, 1000.0 + 41 * PERIOD + LATENCY)  # the stream goes on
    assert acts[0][:3] == (REFUSE, "odometer", bad) and acts[0][3] > TOL
    assert acts[1:] == [(PASS, 1000.0 + 41 * PERIOD)]
    assert f.w.shift == 0.0 and not f.w.held and bad not in f.admitted
    f.run_on(42, 60)


def test_a_late_reading_is_released_by_the_next_one_on_time():
    """Reading 40 comes half a second late (a node that lagged), after 41-44, which came on
    time: below its clock's centre, held for a step. Reading 44 came before it and says nothing
    about it; reading 45, sampled after it arrived, continues the old clock and releases it."""
    f = Feed()
    f.run_on(0, 40)
    f.run_on(41, 45)
    late = 1000.0 + 40 * PERIOD
    assert f.push(late, late + LATENCY + 0.5) == [(HOLD,)]
    assert f.w.doubt()[0] == 1
    nxt = 1000.0 + 45 * PERIOD
    acts = f.push(nxt, nxt + LATENCY)
    assert acts == [(ADMIT, ("odometer", late, {}, late + LATENCY + 0.5, late + LATENCY + 0.5)),
                    (PASS, nxt)]
    assert f.w.shift == 0.0 and not f.w.held and f.admitted[-2:] == [late, nxt]


def test_a_reading_sampled_before_the_held_ones_arrived_does_not_release_them():
    """Readings held as a possible -0.5 s step; a reading of the old clock sampled before the
    first of them arrived (reordered by jitter) is the old clock's late one: admitted, and the
    held ones stay held (released by it, the first readings of a -0.5 s step without a counter
    were fused 0.5 s off their time)."""
    f = Feed()
    f.run_on(0, 40)
    # sample 40 (old clock) is delayed; samples 41, 42 come on the new clock, 0.5 s back
    for k in (41, 42):
        t = 1000.0 + k * PERIOD
        assert f.push(t - 0.5, t + LATENCY) == [(HOLD,)]
    t40 = 1000.0 + 40 * PERIOD
    assert f.push(t40, 1000.0 + 42 * PERIOD + LATENCY + 0.01) == [(PASS, t40)]
    assert len(f.w.held) == 2


def test_at_1_hz_a_late_reading_on_the_grid_is_no_doubt():
    """At 1 Hz a held reading stamped on the stream's sampling phase at a slot not yet filled
    is a late one (no doubt); one off the phase (a backward step) or on a slot already fused is
    in doubt at once; the phase is the stamps' own, whatever the nominal period."""
    f = Feed(period=1.0)
    f.run_on(0, 40)
    late = 1000.0 + 40.0
    assert f.push(late, late + LATENCY + 0.5) == [(HOLD,)]  # below the centre: held
    assert f.w.doubt() == (1, pytest.approx(0.5), False)
    for late, doubt in ((1000.0 + 40 * 1.1, False), (1000.0 + 39 * 1.1 + 1.0, True)):
        g = Feed(period=1.0)
        g.period = 1.1  # stamps 1.1 s apart (a clock 10 % fast): their phase, not the nominal
        g.run_on(0, 40)
        assert g.push(late, late + LATENCY + 0.5) == [(HOLD,)]
        assert g.w.doubt()[2] == doubt
    f = Feed(period=1.0)
    f.run_on(0, 40)
    off = 1000.0 + 39.0 + 0.7  # 0.3 s back, off the grid
    assert f.push(off, 1000.0 + 40.0 + LATENCY) == [(HOLD,)]
    assert f.w.doubt()[2]
    f = Feed(period=1.0)
    f.run_on(0, 40)
    fused = 1000.0 + 38.0  # a slot already fused
    assert f.push(fused, 1000.0 + 40.0 + LATENCY) == [(HOLD,)]
    assert f.w.doubt()[2]


def test_an_unannounced_move_of_the_offset_is_no_drift():
    """A train clock that moves back by 0.5 s on a jittery link without a declared step (the
    window absorbs it): one least-squares fit across the move read it as a drift of -7e-3, and
    the filter's time ran off it. Each level of the offset gets its own intercept."""
    from train_estimation.core.numerics.clocks import StreamClock

    rng = np.random.default_rng(3)
    clock = StreamClock()
    for k in range(1100):
        t = 0.1 * k
        arrival = t + 0.02 + rng.exponential(0.05)
        stamp = t - (0.5 if t >= 50.0 else 0.0)
        clock.add(stamp - arrival, arrival)
        clock.rate_point(stamp, arrival)
    d, se = clock.rate()
    assert abs(d) < 5e-4 and se < 1e-3, (d, se)
    assert clock.value == pytest.approx(-0.57, abs=0.05)



@pytest.mark.parametrize("drain", [1.2, 1.5])
def test_a_queue_that_drains_slowly_is_no_drift(drain):
    """A link that holds the readings for 1 s every 30 s, then delivers them ``drain`` times as
    fast as they were sampled (10 Hz, 20 ms + Exp(30 ms)): the offsets sink by 1 s and climb
    back over seconds, again and again. The rate fit's points off the line scatter wider than
    one level, so they are held and dropped: the drift is the clock's, 0, within its standard
    error. Judged by the offsets' centre, which the drain drags, each episode started a segment
    of the fit whose climb read as slope: +280 ppm at 1.2 in ten minutes."""
    from train_estimation.core.numerics.clocks import StreamClock

    rng = np.random.default_rng(5)
    clock = StreamClock()
    free = -math.inf  # when the queue's server has delivered its backlog
    for k in range(6000):
        t = 0.1 * k
        arrival = t + 0.02 + rng.exponential(0.03)
        if t % 30.0 < 1.0 and t >= 15.0:  # held for the first second of every 30 s
            free = max(free, t - t % 30.0 + 1.0)
        if arrival < free:
            arrival, free = free, free + 0.1 / drain
        clock.add(t - arrival, arrival)
        clock.rate_point(t, arrival)
    d, se = clock.rate()
    assert abs(d) < 5 * se and se < 2e-5, (d, se)

class GridFeed(Feed):
    """A 1 Hz odometer with its sample counter (``seq``) and counted distance (at ``speed``):
    the watch's sample grid learns the stamps against the counter."""

    def __init__(self, speed=10.0):
        super().__init__(period=1.0)
        self.speed = speed  # m/s

    def admit(self, stamp, arrival, fields=None):
        self.w.clock.add(stamp - arrival, arrival)
        seq = fields.get("seq") if fields else None
        self.w.admitted("odometer", stamp, arrival, seq)
        if fields:
            self.w.fused(stamp, fields["distance"], seq)
        self.admitted.append(stamp)

    def push_seq(self, k, raw, arrival):
        fields = {"seq": k, "speed": self.speed, "distance": self.speed * k}
        stamp = self.w.onto_timeline(raw, odometer=True)
        if self.w.last is None:
            self.admit(stamp, arrival, fields)
            return [(PASS, stamp)]
        acts = []
        for act in self.w.watch("odometer", stamp, fields, arrival, arrival):
            acts.append(act)
            if act[0] == ADMIT:
                self.admit(act[1][1], act[1][4], act[1][2])
            elif act[0] == PASS:
                self.admit(act[1], arrival, fields)
        return acts

    def run_jittery(self, rng, n=40, jitter=0.02):
        """Samples 0 .. n - 1 on time, each arriving ``LATENCY`` plus an exponential jitter."""
        for k in range(n):
            t = 1000.0 + k
            assert self.push_seq(k, t, t + LATENCY + rng.exponential(jitter))[-1][0] == PASS

    def then(self, rng, seq_off=0, stamp_off=0.0, k0=40, jitter=0.02):
        """The answers to the next ``min_judged`` samples (from ``k0``), counted ``seq_off``
        samples off and stamped ``stamp_off`` s off, arriving as in :meth:`run_jittery`."""
        return [self.push_seq(k + seq_off, 1000.0 + k + stamp_off,
                              1000.0 + k + LATENCY + rng.exponential(jitter))
                for k in range(k0, k0 + self.w.min_judged)]


def test_a_step_back_at_speed_is_measured_on_the_sample_grid():
    """At 1 Hz and 100 m/s a -3 s step puts the first new reading's stamp on a slot already
    fused, 300 m past the distance fused there: out of reach in the stamps' time, though the
    counters say 3 s passed. Judged by the counters it is a genuine reading, the step's
    readings all lie on the grid, and the step is their grid residual exactly (measured from
    the arrivals it carried the link's jitter)."""
    rng = np.random.default_rng(5)
    f = GridFeed(speed=100.0)
    f.run_jittery(rng, jitter=0.05)
    step = -3.0
    answers = f.then(rng, stamp_off=step, jitter=0.05)
    acts = answers[max(f.w.min_judged, silent_after(0, 40)) - 1]
    assert acts[0][0] == STEP and acts[0][1] == pytest.approx(step, abs=1e-9), acts[0]


@pytest.mark.parametrize("skip", [1, 3, -1])
def test_a_sample_counter_that_skips_is_no_clock_step(skip):
    """The counter jumps by ``skip`` samples while stamps and arrivals run on (a sampling loop that
    missed a cycle and counted it): the grid puts every later reading ``skip`` periods off, the
    arrivals do not move. Held as a possible step until the old clock's silence is a step's at
    the stated risk, and for more readings than a burst of alike wrong stamps (nine after forty
    on time), then the grid learns the counter's new origin and the readings are admitted at
    their own stamps: no step (taken for one at 1 Hz, the estimates ran 81 m off, ALARM for half
    a minute)."""
    rng = np.random.default_rng(7)
    f = GridFeed()
    f.run_jittery(rng)
    answers = f.then(rng, seq_off=skip)
    # 40 samples before, none lost: 6 held readings would make the old clock's silence a
    # step's; min_judged (9) are more than a burst of alike wrong stamps
    n = max(f.w.min_judged, silent_after(0, 40))
    assert n == 9
    assert all(a == [(HOLD,)] for a in answers[:n - 1]), answers
    assert answers[n - 1][0] == (SKIP, skip)
    assert [a[0] for a in answers[n - 1][1:]] == [ADMIT] * n + [HOLD]
    assert all(a == [(PASS, 1000.0 + 40 + k)] for k, a in enumerate(answers) if k >= n)
    assert f.w.shift == 0.0
    assert f.admitted[-len(answers):] == pytest.approx([1000.0 + k for k in range(40, 49)])
    # the stream goes on on the re-learnt grid
    t = 1000.0 + 49
    assert f.push_seq(49 + skip, t, t + LATENCY) == [(PASS, t)]


def test_a_step_of_a_whole_period_is_still_a_step():
    """A -1 s step at 1 Hz moves the grid residual by a whole period too, but the arrivals
    move with it: a clock step."""
    rng = np.random.default_rng(8)
    f = GridFeed()
    f.run_jittery(rng)
    answers = f.then(rng, stamp_off=-1.0)
    acts = answers[max(f.w.min_judged, silent_after(0, 40)) - 1]
    assert acts[0][0] == STEP and acts[0][1] == pytest.approx(-1.0, abs=1e-9)
    assert not any(a[0] == SKIP for ans in answers for a in ans)


def test_kendall_tail_is_the_exact_share_of_orders():
    import itertools

    from train_estimation.core.numerics.clocks import kendall_tail
    for n in range(1, 7):
        perms = list(itertools.permutations(range(n)))
        inv = [sum(p[i] > p[j] for i in range(n) for j in range(i + 1, n)) for p in perms]
        for k in range(n * (n - 1) // 2 + 1):
            assert kendall_tail(n, k) == pytest.approx(sum(v <= k for v in inv) / len(perms),
                                                       rel=1e-12)


def test_a_draining_queue_is_no_step():
    """A link that holds its packets for a second, then delivers them 1.5 times as fast as
    they were sampled: the readings come late by a latency that falls to nothing, so their
    offsets climb back to the clock. Without a sample counter nine of them were taken for a -0.78 s
    step and every later reading was fused that far off its time."""
    rng = np.random.default_rng(3)
    f = Feed()
    acts = []
    for k in range(400):
        t = 1000.0 + k * PERIOD
        lat = LATENCY + rng.exponential(0.03)
        if 200 <= k < 230:  # the queue: 1 s late at k = 200, drained by k = 230
            lat += 1.0 - (k - 200) * PERIOD / 3.0
        acts.append((t + lat, t))
    for arrival, t in sorted(acts):
        for act in f.push(t, arrival):
            assert act[0] != STEP, act
    assert f.w.shift == 0.0
    # every reading judged on its own clock: admitted at its own stamp (late ones rewound)
    assert sorted(f.admitted) == pytest.approx([1000.0 + k * PERIOD for k in range(400)])


def test_a_late_reading_of_a_forward_step_joins_it():
    """After a +0.5 s step the third reading of the new clock arrives 0.33 s late: within the
    bar of the old clock's centre, but above its ceiling, where no latency puts a reading of
    the old clock. It joins the held readings; taken as the old clock's, it released them
    (refused as stamped ahead) and the step was absorbed, 0.5 s off to the end."""
    rng = np.random.default_rng(5)
    f = Feed()
    for k in range(300):
        t = 1000.0 + k * PERIOD
        f.push(t, t + LATENCY + rng.exponential(0.03))
    step, acts = 0.5, []
    # the third 0.33 s late: 0.17 s above the old clock's ceiling, within its bar (0.2 s)
    lats = [0.01, 0.02, 0.33, 0.3] + [0.01] * 12
    assert 0.05 < step - lats[2] - (-LATENCY - f.w.clock.ceiling) < f.w.bar(f.w.clock)
    new = sorted((1000.0 + (300 + i) * PERIOD + LATENCY + lat, 1000.0 + (300 + i) * PERIOD)
                 for i, lat in enumerate(lats))
    for arrival, t in new:
        acts += f.push(t + step, arrival)
    kinds = [a[0] for a in acts]
    assert REFUSE not in kinds
    assert kinds.count(STEP) == 1
    assert f.w.shift == pytest.approx(step, abs=0.05)
    # every reading of the new clock admitted on the old timeline, at its sampling time
    assert f.admitted[-len(lats):] == pytest.approx(
        [1000.0 + (300 + i) * PERIOD for i in range(len(lats))], abs=0.05)


@pytest.mark.parametrize("drift", [-1e-2, 1e-2])
@pytest.mark.parametrize("step", [-0.5, 0.5])
def test_a_step_on_a_drifting_clock_is_measured_against_the_clocks_line(drift, step):
    """A train clock 1 % off, at 1 Hz without a sample counter, 20 ms + Exp(50 ms) of latency,
    steps by ``step`` at 300 s: declared once, and the filter's time after it is where it is
    on the same run without the step (the step measured to the jitter). About a constant
    centre the window's offsets spread over 0.31 s, so the bar (ten robust spreads) hid the
    step; a clock 1 % slow left its ceiling 6 s above the present offsets and hid forward
    steps; and the step was measured from the centre half a window old (0.47 s off)."""
    from train_estimation.core.online.replay import replay
    from train_estimation.core.online.runner import EstimatorRunner
    from train_estimation.tools.clock_runs import SPEED, Recorder, cruise

    def run(with_step):
        rng = np.random.default_rng(0)
        events = cruise(400.0, 1.0, 0.05, False, rng)
        lat = 0.02 + rng.exponential(0.05, len(events))
        out = []
        for (topic, t, f), latency in zip(events, lat):
            if topic == "odometer":
                stamp = 1.7e9 + 1234.5 + t * (1 + drift) + (step if with_step and t >= 300 else 0)
                recv = 1.7e9 + t + latency
            else:  # commands on a clock of their own
                stamp, recv = 1.7e9 + t, 1.7e9 + t + 0.02
            out.append((topic, stamp, f, recv))
        out.sort(key=lambda r: r[3])
        rec = Recorder()
        runner = EstimatorRunner(rec, 1.0)
        replay(out, rec, 1.0, runner=runner)
        fused = np.array(rec.fused).reshape(-1, 2)
        return runner, fused[:, 0] - fused[:, 1] / SPEED

    runner, err = run(True)
    _, clean = run(False)
    assert runner.events.get("odometer:clock_reset", 0) == 1
    assert len(err) == len(clean)
    assert np.max(np.abs(err[-100:] - clean[-100:])) < 0.05, np.max(np.abs(err - clean))


@pytest.mark.parametrize("lost,got,n", [(0, 0, 1), (0, 40, 6), (16, 112, 9), (3, 5, 4),
                                        (60, 4, 2)])
def test_silence_risk_is_the_beta_moment_of_the_loss_rate(lost, got, n):
    """The step's evidence (clocks.silence_risk) against its definition: the loss rate q
    uniform a priori, the ratio of the data's likelihood without a step (the old clock's n
    readings lost too) to that with one, integrated over q numerically."""
    from scipy.integrate import quad

    from train_estimation.core.numerics.clocks import silence_risk
    no_step = quad(lambda q: q ** (lost + n) * (1 - q) ** (got + n), 0.0, 1.0)[0]
    step = quad(lambda q: q ** lost * (1 - q) ** (got + n), 0.0, 1.0)[0]
    assert silence_risk(lost, got, n) == pytest.approx(no_step / step, rel=1e-9)


def test_a_step_needs_more_readings_on_a_lossier_link():
    """The same step at 10 Hz after a minute of readings: decided after the readings the old
    clock's silence needs on that link -- a link that lost none of the minute's readings, one
    that lost one in eight, one that lost every other (the count from silent_after)."""
    counts = {}
    for every in (0, 8, 2):  # a reading lost every ``every`` slots (0: none)
        f = Feed()
        for k in range(600):
            if every and k % every == every - 1:
                continue
            t = 1000.0 + k * PERIOD
            f.push(t, t + LATENCY)
        got = len(f.w._admitted)
        lost = round((f.w._admitted[-1] - f.w._admitted[0]) / PERIOD) + 1 - got
        n = 0
        for k in range(600, 700):
            n += 1
            t = 1000.0 + k * PERIOD
            if f.push(t - 3.0, t + LATENCY)[0][0] == STEP:
                break
        counts[every] = n
        assert n == max(f.w.min_judged, silent_after(lost, got)), (every, n, lost, got)
    assert counts[0] == 9 and counts[8] == 9 and counts[2] > 9, counts
