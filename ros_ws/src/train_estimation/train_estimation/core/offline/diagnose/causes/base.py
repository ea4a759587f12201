"""The protocol every cause implements, with the defaults most causes share.

A cause is one module with one object: its name (docs/interfaces.md), the family of data it acts on,
how it is scored against a stage, how it extends the null when accepted, the
``train_core.effects`` dataclass it becomes (what the simulator runs), its held-out gain, how
it is written into a model directory and what the fleet tracks of it. The search over causes
(``search``) and the fleet know nothing of any particular cause.

Families, in the order the causes are scored: ``motion`` (the dynamics: drift columns of the
motion model), ``odometer`` (measurement columns), ``clock`` (the stamps: a likelihood of its
own) and ``link`` (which messages arrive: a likelihood of its own).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from ..result import CauseFit

FAMILIES = ("motion", "odometer", "clock", "link")

# A fitted change is resolved when it is more than this many standard errors from nominal (and
# more than the cause's stated minimum): 3 SE is a two-sided 0.3 % chance under no change.
Z_RESOLVE = 3.0


def resolved(name: str, delta: float, se, minimum: float, unit: str = "") -> str | None:
    """None when ``|delta|`` (the fitted parameter minus nominal) is more than
    max(Z_RESOLVE x ``se``, ``minimum``), else the reason in words."""
    se = float(se) if se is not None and math.isfinite(float(se)) else 0.0
    need = max(Z_RESOLVE * se, minimum)
    if abs(delta) > need:
        return None
    return (f"below resolution: {name} {delta:+.4g}{unit} from nominal, not more than "
            f"max({Z_RESOLVE:g} SE = {Z_RESOLVE * se:.3g}, minimum {minimum:g}){unit}")


@dataclass(frozen=True)
class ModelContext:
    """What a cause needs to become an effect of a model directory: the run's length on true
    time and the fitted clock drift (times in effects.yaml are true seconds from the start),
    the evidence of the diagnosis and the raw odometer series (stamps s, speeds m/s)."""

    duration: float  # s, true time
    line_length: float  # m, of the believed line
    drift: float  # -, fitted clock drift (0 when not accepted)
    t_first: float  # s, first odometer stamp
    evidence: dict
    odo_stamp: object
    odo_speed: object


class Cause:
    """Defaults: a motion-model cause scored by :meth:`fit` against a stage."""

    name: str = ""
    family: str = "motion"
    linear: bool = False  # parameters a GLS combination of elementary columns (joint refit)
    located: bool = False  # a linear cause whose columns need its fitted place (a section)
    profiled: bool = False  # one nonlinear parameter profiled over a grid (:meth:`profile`)
    effect_name: str = ""  # field of train_core.effects.Effects (default: the cause's name)
    model_file: str = "effects"  # where the model directory holds it: line, train or effects

    @property
    def effect_field(self) -> str:
        return self.effect_name or self.name

    @property
    def in_motion_model(self) -> bool:
        """Scored against the motion model's stages (and refitted at its own noise)."""
        return self.family in ("motion", "odometer")

    # -- testing --------------------------------------------------------------------------------
    def untestable(self, run, cfg, own: dict | None) -> str | None:
        """Why the data cannot test the cause (None: testable)."""
        return None

    def own_test(self, run) -> dict | None:
        """A likelihood of its own, computed once per run (clock, link); None for causes scored
        in the motion model."""
        return None

    def fit(self, st) -> tuple:
        """(ll, k, parameters, standard errors, extra) against the stage ``st``."""
        raise NotImplementedError

    def score(self, st, own: dict | None, ll0: float) -> CauseFit:
        """The cause's fit and BIC score against the stage whose null has log-likelihood
        ``ll0`` (prior odds not yet applied)."""
        if own is not None:
            return CauseFit(self.name, 2 * own["dll"] - own["k"] * math.log(own["n"]),
                            own["parameters"], dll=own["dll"], k=own["k"], n=own["n"],
                            std_errors=own.get("std_errors", {}), extra={})
        n = st.n_meas
        ll, k, params, se, extra = self.fit(st)
        dll = ll - ll0
        return CauseFit(self.name, 2 * dll - k * math.log(n), params, dll=dll, k=k, n=n,
                        std_errors=se, extra=extra)

    def dll_at_noise(self, st, st_c, ll0: float) -> float:
        """Log-likelihood gain of the null extended by the cause (``st_c``, at its own noise)
        over the stage's null ``st`` at that noise: an unmodelled effect inflates the null's
        process noise, which understates the effect's own evidence. The null at the cause's
        noise too: an optimiser that stopped short on the null must not pass for evidence."""
        return st_c.fixed_loglik() - max(ll0, st.loglik_at(st_c.q, st_c.r_s))

    def extend_null(self, null, fit: CauseFit, mo) -> None:
        """Put the fitted cause into the null (in place)."""
        raise NotImplementedError

    # -- linear causes --------------------------------------------------------------------------
    def free(self, st, extra: dict | None = None) -> list:
        """Free combinations of elementary columns: [{column name: weight}]."""
        raise NotImplementedError

    def params(self, st, th, cov, extra: dict | None = None) -> tuple:
        """(parameters, standard errors, extra) from the fitted coefficients."""
        raise NotImplementedError

    def profile(self, st) -> tuple | None:
        """For a cause whose extension is one drift column fixed by one nonlinear parameter: (the
        parameter's name, its candidate values (increasing), the columns on the motion model's
        grid (n_grid, K), m/s^2, one per value), against the stage ``st``'s null; the joint refit
        profiles the parameter with the accepted linear causes free. None: not such a cause."""
        return None

    def fit_linear(self, st) -> tuple:
        free = self.free(st)
        th, cov, ll, _ = st.fit({}, free)
        return (ll, len(free), *self.params(st, th, cov))

    # -- confirmation ---------------------------------------------------------------------------
    def resolution(self, fit: CauseFit, mo) -> str | None:
        """Why the fitted size is not larger than what the data can resolve (None: it is).

        Each cause states its own rule on its reported parameters (``fit.parameters``,
        ``fit.std_errors``; ``mo``: the run's motion model, for the believed train and the
        odometer period), in general with :func:`resolved`: a change is a change only when it
        is more than ``Z_RESOLVE`` standard errors and more than a stated minimum from
        nominal. The default (no rule of its own) accepts every fit."""
        return None

    def plausible(self, fit: CauseFit, mo) -> str | None:
        """Why the fitted cause is not one the railway could have (None: it could): a bound
        that follows from what the cause is (a map's error, a train's parameter), not from the
        data. The default states none."""
        return None

    def plausible_data(self, mo, others, fit: CauseFit, cfg, noise) -> str | None:
        """Like :meth:`plausible`, a bound from what the cause is, but one the data must be
        asked about: ``others`` the model (Null) of the other accepted causes, at ``noise``;
        ``fit`` the cause as fitted. The default states none (and costs nothing)."""
        return None

    # What else makes the same residual when the cause is seen in one phase only (None: the
    # cause acts in one phase by its nature); the confirmation then cannot tell them apart.
    phase_rival: str | None = None

    # ``plausible`` states the range of the cause's parameters (a sign: a braking factor, a
    # drive gain, a scale above 0), a bound on any fit of this cause, not a judgement of an
    # effect's kind from its size (a gradient steeper than a map's error, a clock whose rate
    # turns): a fit outside it is out of the running at the greedy stage (search._refuse).
    range_bound: bool = False

    # A force at a place that grows with speed, which the cause (a force independent of speed
    # at its place) is not; None: the cause states no speed law of its own to test against.
    speed_rival: str | None = None

    # An odometer error that grows with speed, which the cause (one scale at every speed) is
    # not; None: the cause states no count law of its own to test against.
    count_rival: str | None = None

    # An odometer that reads a speed more or less while moving (a scale 1 + b / v that falls
    # with speed), which the cause is not; tested beside ``count_rival`` (its law as rival).
    offset_rival: str | None = None

    # A force fixed at that place (a gradient), which the cause (a force in proportion to the
    # braking asked for at its place) is not; None: the cause is no such law.
    fixed_rival: str | None = None

    # The mirror of ``fixed_rival``: braking weaker in proportion to the braking asked for at
    # that place (a low-adhesion section), which the cause (a force fixed at its place) is not;
    # None: the cause is no force fixed at a place. Both sides are judged by one comparison
    # (check 3's braking law, confirm._braking_verdict), where :meth:`braking_rival_fit` gives
    # a rival the railway could have.
    braking_rival: str | None = None

    def braking_rival_fit(self, fit: CauseFit, mo) -> CauseFit | None:
        """The fit of ``braking_rival`` as a listed cause that gives the effect of ``fit`` on
        its stretch (None: no such fit). The default states none."""
        return None

    # Brakes that fade as they heat (weaker in proportion to the heat of the braking just
    # done, cooling in minutes), which the cause (a braking weaker by a factor in time, or on
    # a stretch) is not; None: the cause is not a weaker braking.
    heat_rival: str | None = None

    # What acts in time rather than at a place and makes the same residual when the stretch
    # is run once (the train is at each place of it at one moment); None: not a cause at a
    # place. Only runs of the stretch at other times (other runs: ``fleet``) tell them apart.
    time_rival: str | None = None

    # The listed cause that acts on the same thing at every place (a low-adhesion section:
    # the braking rate). Where no brake application of the run outside the stretch could
    # show the cause absent there (no cell of the place test where half of it would be a 3 SE
    # departure), "only on this stretch" is a claim the data cannot test, and the search
    # names that cause instead (:func:`..refit.unlocate`); None: no such cause.
    global_rival: str | None = None

    def beyond(self, fit: CauseFit, mo):
        """For a cause fitted on a stretch of track: (inside, pattern), the grid points it acts
        on and its acceleration (m/s^2 per grid point) if it acted at every place in the same
        phases; None for a cause that is not a place effect."""
        return None

    # The quantities whose fits on the held-out check's two folds must agree within their
    # standard errors (:func:`..confirm.halves_test`): names in the fit's parameters or
    # extra, with the standard error under the same name. Empty: no such test (slip episodes:
    # each fold holds every episode, but its depth is the one quantity and is held out
    # episode by episode).
    halves: tuple = ()

    # A cause at a place: (its quantity's name, the quantity from the fitted column's
    # coefficient) for the halves of its stretch (:func:`..halves.place_halves`, with the
    # cause's ``half_columns``); None: not such a cause.
    half_quantity: tuple | None = None

    def halves_own(self, mo, others, cfg, noise, alpha: float, min_share: float,
                   fit: CauseFit | None = None) -> dict | None:
        """A halves test of the cause's own in place of the comparison of the held-out
        folds' fits (:func:`..confirm.halves_test`'s form), against the model ``others``
        without the cause at ``noise`` (``fit``: the whole data's fit); None: the folds' fits
        are compared. A sensor's folds are alternate samples, which both hold the whole run:
        its halves are halves of the run (:mod:`..halves`); a cause at a place
        (:attr:`half_quantity`) keeps the stretch the whole data found and compares its size on
        the stretch's halves (:func:`..halves.place_halves`)."""
        if self.half_quantity is None:
            return None
        from ..halves import place_halves

        return place_halves(mo, others, self, fit, cfg, noise, alpha, min_share)

    def nominal(self, mo) -> dict:
        """{quantity of :attr:`halves`: its believed value} (the cause's size is a fit's change
        from it); {} where there is none (a power limit the believed train does not have)."""
        return {}

    def halves_values(self, params: dict, se: dict, extra: dict) -> dict:
        """{name: (value, standard error)} of :attr:`halves` in one fold's fit (those with a
        finite positive standard error)."""
        out = {}
        for k in self.halves:
            v = params.get(k, (extra or {}).get(k))
            e = (se or {}).get(k)
            try:
                v, e = float(v), float(e)
            except (TypeError, ValueError):
                continue
            if math.isfinite(v) and math.isfinite(e) and e > 0:
                out[k] = (v, e)
        return out

    # -- what it becomes ------------------------------------------------------------------------
    def report(self, params: dict, beta: float) -> dict:
        """Parameters as docs/interfaces.md reports them (times on the train's stamp clock)."""
        return params

    def effect(self, params: dict, duration: float):
        """The train_core.effects dataclass of the fitted cause (``duration``: s, the run's
        length on the time axis of the parameters)."""
        raise NotImplementedError

    def clock_drift(self, fit: CauseFit) -> float:
        """-, the train clock's drift the accepted cause implies (times in a model directory
        are true seconds)."""
        return 0.0

    def model_effect(self, fit: CauseFit, ctx: ModelContext):
        """(effect, note) for a model directory, or (None, reason) when the fit cannot be
        written (the effect's own parameter ranges are checked by its parser)."""
        return self.effect(fit.parameters, ctx.duration), None

    def replay_offset(self, extra: dict, shift: float) -> float:
        """s, command-time offset the extended model replays the commands with (the
        analysis' nuisance offset unless the cause fits its own timing)."""
        return shift

    def gain(self, fit: CauseFit, ctx) -> dict:
        """How much better the extended model predicts data not used for the fit."""
        from ..gain import gain_motion

        return gain_motion(self, ctx)

    def series(self, params: dict, mo, out: dict) -> None:
        """Add the accepted cause's curves to the plots' series (in place)."""

    def own_series(self, own: dict, out: dict) -> None:
        """Add what the cause's own likelihood test saw to the plots' series (in place),
        accepted or not."""

    # -- the fleet ------------------------------------------------------------------------------
    def fleet_row(self, fit: CauseFit, evidence: dict, accepted: bool, train) -> dict:
        """What the fleet's consensus tracks of this cause in one run: {column: value} from the
        ranking entry ``fit`` (parameters as reported, fitted with the accepted causes in the
        model), the cause's ``evidence`` (standard errors, details), whether it was
        ``accepted``, and the believed ``train``; {} when the fleet tracks nothing of it."""
        return {}


def fleet_se(evidence: dict, key: str) -> float | None:
    """A standard error of the evidence the fleet can weigh by: finite and positive, else None."""
    v = (evidence.get("std_errors") or {}).get(key)
    return v if v is not None and math.isfinite(v) and v > 0 else None
