"""Line.gradient_permille / gradient_accel by bisection (a real line has hundreds of sections):
exactly what the loop over sections gives, at every position, for scalars and arrays, sorted or
not, with gaps, and with overlapping sections (the last listed wins)."""

import math

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from train_core.model import G, GradientSection, Line


def loop_oracle(line: Line, x):
    out = np.zeros_like(np.asarray(x, dtype=float))
    for s in line.gradients:
        out = np.where((x >= s.start) & (x < s.end), s.permille, out)
    return out


@st.composite
def lines(draw, overlapping=False):
    n = draw(st.integers(0, 40))
    secs = []
    for _ in range(n):
        a = draw(st.integers(0, 5000))
        b = a + draw(st.integers(1, 800))
        secs.append(GradientSection(float(a), float(b), float(draw(st.integers(-40, 40)))))
    if not overlapping:  # keep a non-overlapping subset in a random order
        keep, last = [], -1.0
        for s in sorted(secs, key=lambda s: s.start):
            if s.start >= last:
                keep.append(s)
                last = s.end
        secs = draw(st.permutations(keep))
    return Line("l", 6000.0, gradients=tuple(secs))


@settings(max_examples=150, deadline=None)
@given(st.one_of(lines(), lines(overlapping=True)))
def test_lookup_equals_the_loop_over_sections(line):
    x = np.concatenate([np.linspace(-10.0, 6010.0, 2001),
                        [s.start for s in line.gradients], [s.end for s in line.gradients],
                        [np.nextafter(s.end, -np.inf) for s in line.gradients]])
    want = loop_oracle(line, x)
    assert np.array_equal(line.gradient_permille(x), want)
    for xi, w in zip(x[::7], want[::7]):
        got = line.gradient_permille(float(xi))
        assert isinstance(got, float) and got == w
        p = w / 1000.0
        assert line.gradient_accel(float(xi)) == G * p / math.sqrt(1.0 + p * p)
    assert np.array_equal(line.gradient_accel(x), G * (want / 1e3) / np.sqrt(1 + (want / 1e3) ** 2))
