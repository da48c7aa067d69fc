"""Propagation of distributions (JCGM 101) and the law of propagation (GUM), for any model.

    res = propagate(model, inputs, coverage=0.95, trials=None, seed=1, correlations=None)

``model(**arrays)`` receives one pint Quantity array per input (leading trial
axis) and returns a Quantity array, one value per trial, each computed from
that trial's inputs alone (JCGM 101's y_r = f(x_r)): the model is evaluated
on consecutive blocks of at most :data:`EVAL_BLOCK` trials (whose
temporaries stay in cache), and the GUF evaluates it on the expectations
and their neighbours in one call.  ``trials=None`` runs the adaptive
procedure of JCGM 101 7.9; an int runs exactly that many trials.

The GUF side uses the ``uncertainties`` package for the law of propagation
(first order, correlations included) with sensitivity coefficients from
central differences of the model at the input expectations, and
Welch-Satterthwaite for the effective degrees of freedom.

Several outputs (JCGM 102): a model that returns a dict of named Quantity arrays gets a :class:`MultiResult`:
``names``, ``outputs[name]`` (each the univariate :class:`Result` above, with its own GUF and budget),
``covariance`` and ``correlation`` (numpy arrays in the order of ``names``), ``gum`` (:class:`MultiGUF`: the
sensitivity matrix C_x and U_y = C_x U_x C_x^T, JCGM 102 6.2), ``region(kind)`` (hyperellipsoidal or
hyperrectangular coverage regions, JCGM 102 7.7; ``gum.region`` the GUF's, 6.5) and ``validate()`` (clause 8 for
several outputs, :class:`MultiValidation`).  Every output is computed from the same trials (the same input draws).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import pint
import uncertainties

from .distributions import Distribution, Normal, t_factor
from .errors import ModelError
from .stats import AdaptiveStop, batch_row, clause8, percent, shortest_interval, symmetric_interval
from .units import Q_



@dataclass
class BudgetRow:
    name: str
    distribution: str
    std_uncertainty: pint.Quantity  # u(x_i)
    sensitivity: pint.Quantity  # c_i
    contribution: pint.Quantity  # |c_i| u(x_i)
    share: float  # (c_i u(x_i))^2 / u_c^2 (independent inputs)
    dof: float


@dataclass
class GUFResult:
    estimate: pint.Quantity
    std_uncertainty: pint.Quantity
    dof: float
    coverage: float
    sensitivities: dict = field(default_factory=dict)

    def interval(self, coverage: float | None = None):
        p = self.coverage if coverage is None else coverage
        k = t_factor(p, self.dof)
        return (self.estimate - k * self.std_uncertainty, self.estimate + k * self.std_uncertainty)

    @property
    def coverage_factor(self) -> float:
        return t_factor(self.coverage, self.dof)


@dataclass
class Validation:
    """JCGM 101 clause 8: GUF interval vs MCM interval."""

    d_low: pint.Quantity
    d_high: pint.Quantity
    delta: pint.Quantity
    passed: bool

    def __str__(self):
        verdict = "GUF validated" if self.passed else "GUF not validated"
        return f"{verdict}: d_low = {self.d_low:~.3g}, d_high = {self.d_high:~.3g}, delta = {self.delta:~.3g}"


@dataclass
class Result:
    """The Monte Carlo result: the trial values and what JCGM 101 7.6-7.7 makes of them.

    ``values`` are the trials' output magnitudes (output units), the Result's own array, in trial order until
    ``samples`` (the same values, sorted) is first used: the estimate, the standard uncertainty and the
    probabilistically symmetric interval do not need the sort (the interval's two order statistics are picked
    out exactly, see :func:`_order_statistic`), the shortest interval does.
    """

    values: np.ndarray  # output magnitudes, trial order until sorted (then sorted in place)
    units: pint.Unit
    coverage: float
    gum: GUFResult
    budget: list
    ndig: int = 2
    batches: list = field(default_factory=list)  # adaptive: (M, y, u, low, high) per batch
    is_sorted: bool = False
    _mean: float | None = field(default=None, init=False, repr=False, compare=False)  # cached
    _std: float | None = field(default=None, init=False, repr=False, compare=False)  # cached

    @property
    def samples(self) -> np.ndarray:
        """The trial values (magnitudes, output units), sorted."""
        if not self.is_sorted:
            self.std_uncertainty  # noqa: B018 - the mean and u first, summed in trial order whatever is asked first
            self.values.sort()  # in place: the Result's own array; the same numbers in another order
            self.is_sorted = True
        return self.values

    @property
    def trials(self) -> int:
        return int(self.values.shape[0])

    def __repr__(self) -> str:
        """What the result is, in one line (never the trial values themselves)."""
        lo, hi = self.interval("symmetric")
        unit, u = f"{self.units:~P}", self.std_uncertainty.magnitude
        # y and the interval to the decimal of u's second significant digit (GUM 7.2.6)
        d = max(0, 1 - math.floor(math.log10(u))) if u > 0 and math.isfinite(u) else 6
        f = (lambda x: f"{x:.{d}f}") if d <= 12 else (lambda x: f"{x:.6g}")
        return (f"<mtbudget MCM result: y = {f(self.estimate.magnitude)} {unit}, u(y) = {u:.2g} {unit} (standard "
                f"uncertainty, k = 1), {100 * self.coverage:g} % probabilistically symmetric coverage interval "
                f"[{f(lo.magnitude)}, {f(hi.magnitude)}] {unit}; M = {self.trials} trials (JCGM 101)>")

    @property
    def estimate(self) -> pint.Quantity:
        if self._mean is None:
            self._mean = float(self.values.mean())
        return Q_(self._mean, self.units)

    @property
    def std_uncertainty(self) -> pint.Quantity:
        if self._std is None:
            self._std = _std(self.values, self.estimate.magnitude)
        return Q_(self._std, self.units)

    def interval(self, kind: str = "symmetric", coverage: float | None = None):
        p = self.coverage if coverage is None else coverage
        if kind == "symmetric":
            lo, hi = symmetric_interval(self.samples if self.is_sorted else _OrderStatistics(self.values), p)
        elif kind == "shortest":
            lo, hi = shortest_interval(self.samples, p)
        else:
            raise ValueError(f"interval kind must be 'symmetric' or 'shortest', got {kind!r}")
        return Q_(lo, self.units), Q_(hi, self.units)

    def validate(self, kind: str = "symmetric", ndig: int | None = None) -> Validation:
        """Compare the GUF interval with the MCM interval (JCGM 101 8.2)."""
        nd = self.ndig if ndig is None else ndig
        mag = lambda pair: [q.to(self.units).magnitude for q in pair]  # noqa: E731
        d_low, d_high, delta, ok = clause8(mag(self.gum.interval()), mag(self.interval(kind)),
                                           self.gum.std_uncertainty.to(self.units).magnitude, nd)
        return Validation(Q_(d_low, self.units), Q_(d_high, self.units), Q_(delta, self.units), ok)


_BLOCK = 65536  # values per block of the blockwise reductions (0.5 MB: in cache)


def _std(y: np.ndarray, mean: float) -> float:
    """The standard deviation of y about its mean (ddof = 1), in two passes as numpy's ``std``; blockwise, the
    deviations of a block in cache (no temporary of len(y) values)."""
    n = y.shape[0]
    if n < 2:
        return math.nan
    buf = np.empty(min(n, _BLOCK))
    ss = 0.0
    for s in range(0, n, buf.size):
        d = buf[:min(buf.size, n - s)]
        np.subtract(y[s:s + d.size], mean, out=d)
        np.square(d, out=d)
        ss += float(d.sum())  # numpy's pairwise sum (np.dot would go to BLAS and its threads)
    return math.sqrt(ss / (n - 1))


def _order_statistic(y: np.ndarray, k: int) -> float:
    """The k-th smallest value of y (0-based; y finite): exactly ``np.sort(y)[k]``, without sorting y.

    A strided sample of about 8192 values of y (the trials are independent: any fixed subset is a random
    sample) places a bound a few binomial standard deviations beyond k on k's side; the values of y beyond the
    bound (for a coverage interval's end, a few per cent of y) are picked out and partitioned.  The bound is
    checked by counting: if fewer than needed lie beyond it (improbable), y is sorted (a copy).
    """
    n = y.shape[0]
    if n <= 65536:
        return float(np.partition(y, k)[k])
    sub = np.sort(y[::n // 8192])
    s = sub.shape[0]
    top = k >= n // 2
    j = n - 1 - k if top else k  # the rank from the nearer end
    e = j * s / n  # its expected place in the sample, from the same end
    i = min(s - 1, int(e + 6 * math.sqrt(e + 1) + 8))
    # the j + 1 values of y nearest its end are among those beyond the bound if there are more than j of them;
    # picked out by index (flatnonzero is branch-free: faster than a boolean index, which copies run by run)
    cand = y.take(np.flatnonzero(y >= sub[s - 1 - i] if top else y <= sub[i]))
    if cand.size > j:
        at = cand.size - 1 - j if top else j
        return float(np.partition(cand, at)[at])
    return float(np.sort(y)[k])


class _OrderStatistics:
    """y as its sorted values for :func:`stats.symmetric_interval` (``shape``, ``[k]``), without sorting y."""

    def __init__(self, y: np.ndarray):
        self.y, self.shape = y, y.shape

    def __getitem__(self, k: int) -> float:
        return _order_statistic(self.y, int(k))


def _as_distribution(name, d) -> Distribution:
    if isinstance(d, Distribution):
        return d
    raise ModelError(f"input {name!r}: expected a Distribution from mtbudget.distributions, got {type(d).__name__}")


#: trials per call of the model (the last block may be shorter): 2^17 values, 1 MB an array, measured best among
#: 2^13-2^18 for JCGM 101 9.4 and 9.5 (smaller blocks pay pint's overhead per call more often)
EVAL_BLOCK = 131072

#: threads that draw the inputs of one run (each input from its own stream, so the numbers do not depend on
#: this); 1 draws them one after the other (what is left when the other cores are busy)
DRAW_THREADS = 2


def _sample_inputs(inputs: dict, n: int, seed_seq: np.random.SeedSequence, corr: np.ndarray | None, names: list) -> dict:
    """Draw every input; each from its own stream (so the draws do not depend on threads or order)."""
    children = seed_seq.spawn(len(names) + 1)
    out = {}
    if corr is not None:
        L = np.linalg.cholesky(corr)
        z = L @ np.random.default_rng(children[-1]).standard_normal((len(names), n))
        for i, k in enumerate(names):
            out[k] = Q_(inputs[k].standard_normal_map(z[i]), inputs[k].units)
        return out

    def draw(i):
        return names[i], inputs[names[i]].sample(n, np.random.default_rng(children[i]))

    if n >= 200_000 and len(names) > 1 and DRAW_THREADS > 1:
        # numpy's generators release the GIL while filling large arrays: draw the inputs on both cores
        from concurrent.futures import ThreadPoolExecutor

        with ThreadPoolExecutor(max_workers=DRAW_THREADS) as pool:
            return dict(pool.map(draw, range(len(names))))
    return dict(draw(i) for i in range(len(names)))


def _correlation_matrix(inputs: dict, names: list, correlations: dict | None):
    if not correlations:
        return None
    R = np.eye(len(names))
    for key, r in correlations.items():
        if not (isinstance(key, tuple) and len(key) == 2):
            raise ModelError(f"correlations keys must be (name, name) pairs, got {key!r}")
        a, b = key
        for x in (a, b):
            if x not in inputs:
                raise ModelError(f"correlation names unknown input {x!r}")
            if not isinstance(inputs[x], Normal):
                raise ModelError(f"correlation of {x!r}: only Normal inputs can be correlated (JCGM 101 6.4.8); it is {inputs[x].describe()}")
        if not -1 <= r <= 1:
            raise ModelError(f"correlation {key}: {r} is outside [-1, 1]")
        i, j = names.index(a), names.index(b)
        R[i, j] = R[j, i] = r
    w = np.linalg.eigvalsh(R)
    if w.min() <= 1e-12:
        raise ModelError(f"the correlation matrix is not positive definite (smallest eigenvalue {w.min():.3g})")
    return R


def _evaluate(model, arrays: dict, names: list) -> pint.Quantity | dict:
    """The model's value: a Quantity, or a dict of named outputs (JCGM 102) as the model returned it."""
    try:
        y = model(**arrays)
    except pint.DimensionalityError as exc:
        units = ", ".join(f"{k} [{v.units:~}]" for k, v in arrays.items())
        raise ModelError(f"the model's units do not fit its inputs ({exc}); inputs: {units}") from None
    if isinstance(y, dict):
        return y
    if not isinstance(y, pint.Quantity):
        y = Q_(np.asarray(y, float))
    return y


def _check_nan(y: np.ndarray, arrays: dict):
    bad = ~np.isfinite(y)
    if bad.any():
        idx = np.flatnonzero(bad)
        first = idx[0]
        vals = ", ".join(f"{k}={v[first]:~.6g}" for k, v in arrays.items())
        raise ModelError(f"the model returned NaN or infinity for {idx.size} of {y.size} trials; "
                         f"the first (trial {first}) had inputs {vals}")


def _guf_points(inputs: dict, names: list):
    """The model's arguments for the GUF: one evaluation on 1 + 2 n values (column 0 the expectations, columns
    1 + 2 i and 2 + 2 i input i moved by +h and -h), as the Monte Carlo evaluates it; (arguments, steps)."""
    means = {k: inputs[k].mean for k in names}
    us = {k: inputs[k].gum_std for k in names}
    steps, cols = {}, {}
    for i, k in enumerate(names):
        u = us[k].magnitude
        steps[k] = h = u * 1e-4 if u > 0 else max(abs(means[k].magnitude) * 1e-8, 1e-12)
        col = np.full(1 + 2 * len(names), float(means[k].magnitude))
        col[1 + 2 * i] += h
        col[2 + 2 * i] -= h
        cols[k] = Q_(col, means[k].units)
    return cols, steps


def _central(y: pint.Quantity, names: list, steps: dict):
    """(units, y at the expectations, {input: central-difference sensitivity}) from the model's values at the
    GUF points (:func:`_guf_points`)."""
    n = 1 + 2 * len(names)
    ym = np.asarray(y.magnitude, float)
    if ym.size not in (1, n):
        raise ModelError(f"the model must return one value per trial, shape ({n},) for {n} trials; got shape "
                         f"{ym.shape} (several outputs: return a dict of named outputs, JCGM 102)")
    ym_all = np.broadcast_to(ym.ravel(), (n,))
    sens = {k: float((ym_all[1 + 2 * i] - ym_all[2 + 2 * i]) / (2 * steps[k])) for i, k in enumerate(names)}
    return y.units, float(ym_all[0]), sens


def gum(model, inputs: dict, coverage: float = 0.95, correlations: dict | None = None) -> tuple[GUFResult, list]:
    """Law of propagation (GUM 5.1/5.2) with numerical sensitivities and Welch-Satterthwaite."""
    names = list(inputs)
    cols, steps = _guf_points(inputs, names)
    with np.errstate(all="ignore"):  # an overflow here is reported below, naming the input
        y = _evaluate(model, cols, names)
        if isinstance(y, dict):
            raise ModelError(f"the model returns several outputs ({', '.join(map(str, y))}): use propagate() or "
                             "gum_multi() (JCGM 102)")
        out_units, y0m, sens = _central(y, names, steps)
    return _guf_scalar(inputs, names, y0m, sens, out_units, coverage, _correlation_matrix(inputs, names, correlations))


def _guf_scalar(inputs, names, y0m, sens, out_units, coverage, R):
    """The GUF of one output from its value at the expectations and its sensitivities: (GUFResult, budget rows)."""
    means = {k: inputs[k].mean for k in names}
    us = {k: inputs[k].gum_std for k in names}
    rows = []
    # uncertainties: inputs as (correlated) ufloats about 0, the output as their linear combination
    try:
        if R is not None:
            cov = R * np.outer([us[k].magnitude for k in names], [us[k].magnitude for k in names])
            xs = uncertainties.correlated_values(np.zeros(len(names)), cov, tags=names)
        else:
            xs = [uncertainties.ufloat(0.0, us[k].magnitude, tag=k) for k in names]
        y = y0m + sum(sens[k] * x for k, x in zip(names, xs))
        uc = float(y.std_dev)
    except (OverflowError, ValueError) as exc:  # u or c u beyond double precision: say which input, not where
        worst = max(names, key=lambda k: abs(sens[k] * us[k].magnitude) if math.isfinite(sens[k]) else math.inf)
        raise ModelError(f"the law of propagation of uncertainty overflows ({exc}): the contribution of input "
                         f"{worst!r} (u = {us[worst].magnitude:.3g} {us[worst].units:~}, sensitivity {sens[worst]:.3g}) "
                         "is beyond double precision; state the inputs in units that keep them in range") from None
    if not math.isfinite(uc) or not all(math.isfinite(v) for v in sens.values()):
        bad = [k for k in names if not math.isfinite(sens[k])] or names
        raise ModelError(f"the law of propagation of uncertainty gives a non-finite u(y) (sensitivity to "
                         f"{', '.join(repr(k) for k in bad)} not finite): check the model and the inputs' scales")
    denom = 0.0
    for k in names:
        ci_ui = sens[k] * us[k].magnitude
        nu = inputs[k].gum_dof
        if ci_ui and not math.isinf(nu):
            denom += ci_ui**4 / nu
    dof = math.inf if denom == 0 else uc**4 / denom
    for k in names:
        ci_ui = sens[k] * us[k].magnitude
        rows.append(BudgetRow(
            name=k, distribution=inputs[k].describe(), std_uncertainty=us[k],
            sensitivity=Q_(sens[k], out_units / means[k].units), contribution=Q_(abs(ci_ui), out_units),
            share=(ci_ui**2 / uc**2) if uc > 0 else 0.0, dof=inputs[k].gum_dof,
        ))
    g = GUFResult(Q_(y0m, out_units), Q_(uc, out_units), dof, coverage,
                  {k: Q_(v, out_units / means[k].units) for k, v in sens.items()})
    return g, rows


def propagate(model, inputs: dict, coverage: float = 0.95, trials: int | None = None, seed: int | None = 1,
              correlations: dict | None = None, ndig: int = 2, batch: int | None = None,
              max_trials: int = 50_000_000) -> Result | MultiResult:
    """Monte Carlo propagation (JCGM 101) with the GUF alongside; see the module docstring.  A model that returns a
    dict of named outputs gets a :class:`MultiResult` (JCGM 102)."""
    if not 0 < coverage < 1:
        raise ModelError(f"coverage must lie in (0, 1), got {coverage}")
    inputs = {k: _as_distribution(k, v) for k, v in inputs.items()}
    names = list(inputs)
    R = _correlation_matrix(inputs, names, correlations)
    ss = np.random.SeedSequence(seed)
    probe = _evaluate(model, {k: Q_(np.array([float(inputs[k].mean.magnitude)]), inputs[k].units) for k in names}, names)
    if isinstance(probe, dict):  # several outputs: JCGM 102
        if not probe:
            raise ModelError("the model returned an empty dict: name at least one output")
        return _propagate_multi(model, inputs, names, correlations, coverage, trials, ss, ndig, batch, max_trials)
    g, rows = gum(model, inputs, coverage, correlations)
    out_units = g.estimate.units

    def values(y, n):
        try:
            ym = np.asarray(y.to(out_units).magnitude, float)
        except pint.DimensionalityError:
            raise ModelError(f"the model's output changed units between calls ({y.units:~} vs {out_units:~})") from None
        if ym.shape != (n,) and ym.size != 1:
            raise ModelError(f"the model must return one value per trial, shape ({n},); got shape {np.shape(y.magnitude)}")
        return ym

    def run(n, child):
        """(the trial values, a fresh array of the run's own, their sum)."""
        arrays = _sample_inputs(inputs, n, child, R, names)
        ym = np.empty(n)
        mags = [(k, q.magnitude, q.units) for k, q in arrays.items()]
        for s in range(0, n, EVAL_BLOCK):  # block by block: the model's temporaries stay in cache
            e = min(n, s + EVAL_BLOCK)
            part = arrays if e - s == n else {k: Q_(m[s:e], u) for k, m, u in mags}
            ym[s:e] = values(_evaluate(model, part, names), e - s)
        total = float(ym.sum())  # NaN or infinite if any value is (or, rarely, if the sum overflows): then look
        if not math.isfinite(total):
            _check_nan(ym, arrays)
        return ym, total

    if trials is not None:
        if int(trials) < 2:
            raise ModelError(f"trials must be >= 2, got {trials}")
        y, total = run(int(trials), ss.spawn(1)[0])
        res = Result(y, out_units, coverage, g, rows, ndig)  # sorted only when needed
        res._mean = total / y.shape[0]  # what numpy's mean gives: the same pairwise sum, divided by the count
        return res

    # adaptive Monte Carlo procedure (JCGM 101 7.9)
    h_size = batch or max(int(100 / (1 - coverage)), 10_000)
    parts, stop = [], AdaptiveStop(ndig)
    for child in iter(lambda: ss.spawn(1)[0], None):
        y = run(h_size, child)[0]
        y.sort()  # in place: the run's own array
        parts.append(y)
        stop.add(batch_row(y, coverage, presorted=True))
        allu = np.concatenate(parts).std(ddof=1)  # the batches in order, each sorted
        if stop.done(allu) or len(stop.batches) * h_size >= max_trials:
            break
    ally = np.concatenate(parts)
    ally.sort()  # in place: a fresh array
    return Result(ally, out_units, coverage, g, rows, ndig,
                  batches=[(h_size * (i + 1),) + tuple(map(float, st[0])) for i, st in enumerate(stop.batches)],
                  is_sorted=True)


# ------------------------------------------------------------------ several outputs (JCGM 102)
@dataclass
class CoverageRegion:
    """A coverage region for several outputs (JCGM 102 6.5 for the GUF, 7.7 for the MCM).

    ``kind`` "hyperellipsoidal": the points eta with (eta - y)^T U_y^-1 (eta - y) <= k^2; "hyperrectangular": the
    points with |eta_j - y_j| <= k u(y_j) for every output j (``half_widths``).  ``center``, ``covariance`` and
    ``half_widths`` are magnitudes in ``units`` (one unit per output, in the order of ``names``).
    """

    kind: str
    names: list
    units: list
    center: np.ndarray
    covariance: np.ndarray
    k: float
    coverage: float
    method: str

    @property
    def half_widths(self) -> np.ndarray:
        return self.k * np.sqrt(np.diagonal(self.covariance))

    def contains(self, points) -> np.ndarray:
        """Whether each point ((m,) or (N, m) magnitudes in ``units``) lies in the region."""
        d = np.atleast_2d(np.asarray(points, float)) - self.center
        if self.kind == "hyperellipsoidal":
            return np.einsum("ni,ni->n", d @ np.linalg.inv(self.covariance), d) <= self.k**2
        return np.all(np.abs(d) <= self.half_widths, axis=1)

    def __str__(self) -> str:
        if self.kind == "hyperellipsoidal":
            shape = f"(eta - y)' U_y^-1 (eta - y) <= {self.k:.4g}^2"
        else:
            shape = ", ".join(f"|{n} - y| <= {h:.3g} {u:~P}" for n, u, h in zip(self.names, self.units, self.half_widths))
        return (f"{percent(self.coverage)} {self.kind} coverage region of ({', '.join(self.names)}): {shape} "
                f"(k = {self.k:.4g}; {self.method})")


def _normal_rectangle_k(R: np.ndarray, p: float) -> tuple[float, str]:
    """k such that a normal vector of correlation R has |Z_j| <= k for every j with probability p, and how."""
    from scipy import optimize, stats

    m = R.shape[0]
    k_indep = float(stats.norm.ppf((1 + p ** (1 / m)) / 2))  # Sidak: exact for independent outputs, an upper bound
    if m == 1:
        return float(stats.norm.ppf((1 + p) / 2)), "normal quantile"
    if m > 20:
        return k_indep, "Sidak's bound for independent outputs (coverage at least p; more than 20 outputs)"
    mvn = stats.multivariate_normal(np.zeros(m), R, allow_singular=True, seed=1)
    f = lambda k: float(mvn.cdf(np.full(m, k), lower_limit=np.full(m, -k))) - p  # noqa: E731
    lo = float(stats.norm.ppf((1 + p) / 2))
    if f(k_indep) <= 0:
        return k_indep, "Sidak's bound"
    return float(optimize.brentq(f, lo, k_indep, xtol=1e-6)), "multivariate normal probability (Genz)"


@dataclass
class MultiGUF:
    """The GUM uncertainty framework for several outputs (JCGM 102 6.2): U_y = C_x U_x C_x^T.

    ``sensitivity`` is C_x, (outputs, inputs), in output units per input unit (``sensitivity_units``);
    ``input_covariance`` U_x in the inputs' units, ``covariance`` U_y in the outputs' units; ``outputs[name]`` the
    univariate GUF of each output (its budget, Welch-Satterthwaite degrees of freedom) as :func:`gum` gives it.
    """

    names: list
    units: list
    estimate: np.ndarray
    input_names: list
    sensitivity: np.ndarray
    input_covariance: np.ndarray
    covariance: np.ndarray
    coverage: float
    outputs: dict
    budgets: dict

    @property
    def sensitivity_units(self) -> list:
        return [[self.outputs[n].sensitivities[k].units for k in self.input_names] for n in self.names]

    @property
    def std_uncertainty(self) -> np.ndarray:
        return np.sqrt(np.diagonal(self.covariance))

    @property
    def correlation(self) -> np.ndarray:
        return _correlation_of(self.covariance)

    def region(self, kind: str = "hyperellipsoidal", coverage: float | None = None) -> CoverageRegion:
        """JCGM 102 6.5: the region of a multivariate normal of mean y and covariance U_y."""
        from scipy import stats

        p = self.coverage if coverage is None else coverage
        m = len(self.names)
        if kind == "hyperellipsoidal":
            k, how = math.sqrt(stats.chi2.ppf(p, m)), "GUF: chi-squared quantile with m degrees of freedom (JCGM 102 6.5.2)"
        elif kind == "hyperrectangular":
            k, how = _normal_rectangle_k(self.correlation, p)
            how = f"GUF: {how} (JCGM 102 6.5.4)"
        else:
            raise ValueError(f"region kind must be 'hyperellipsoidal' or 'hyperrectangular', got {kind!r}")
        return CoverageRegion(kind, list(self.names), list(self.units), self.estimate.copy(), self.covariance.copy(),
                              k, p, how)


def _correlation_of(cov: np.ndarray) -> np.ndarray:
    s = np.sqrt(np.diagonal(cov))
    with np.errstate(invalid="ignore", divide="ignore"):
        r = cov / np.outer(s, s)
    np.fill_diagonal(r, 1.0)
    return r


def gum_multi(model, inputs: dict, coverage: float = 0.95, correlations: dict | None = None) -> MultiGUF:
    """The GUF for a model that returns a dict of named outputs (JCGM 102 6.2), sensitivities by central
    differences as :func:`gum`."""
    inputs = {k: _as_distribution(k, v) for k, v in inputs.items()}
    names = list(inputs)
    cols, steps = _guf_points(inputs, names)
    with np.errstate(all="ignore"):
        y = _evaluate(model, cols, names)
    if not isinstance(y, dict):
        raise ModelError("gum_multi: the model must return a dict of named outputs")
    R = _correlation_matrix(inputs, names, correlations)
    outs, units, est, C, guf, budgets = list(y), [], [], [], {}, {}
    for o in outs:
        yo = y[o] if isinstance(y[o], pint.Quantity) else Q_(np.asarray(y[o], float))
        with np.errstate(all="ignore"):  # a non-finite sensitivity is reported by _guf_scalar, naming the input
            u_, y0, sens = _central(yo, names, steps)
        g, rows = _guf_scalar(inputs, names, y0, sens, u_, coverage, R)
        units.append(u_)
        est.append(y0)
        C.append([sens[k] for k in names])
        guf[o], budgets[o] = g, rows
    us = np.array([inputs[k].gum_std.magnitude for k in names])
    Ux = np.outer(us, us) * (np.eye(len(names)) if R is None else R)
    C = np.array(C)
    return MultiGUF(outs, units, np.array(est), names, C, Ux, C @ Ux @ C.T, coverage, guf, budgets)


@dataclass
class MultiValidation:
    """JCGM 102 clause 8 as mtbudget applies it: each output's GUF interval against its MCM interval (JCGM 101 8.2,
    delta from u(y_j) to ``ndig`` significant digits) and every correlation coefficient of the GUF against the
    MCM's (to ``ndig`` decimals: delta_r = 0.5 10^-ndig); the coverage factors of both regions are given beside."""

    outputs: dict  # name -> Validation
    correlation_difference: np.ndarray
    delta_r: float
    k: dict  # kind -> (GUF k, MCM k)
    passed: bool

    def __str__(self):
        verdict = "GUF validated" if self.passed else "GUF not validated"
        per = "; ".join(f"{n}: {'ok' if v.passed else 'fails'}" for n, v in self.outputs.items())
        return (f"{verdict} (JCGM 102 clause 8): {per}; largest |r_GUF - r_MCM| = "
                f"{np.max(self.correlation_difference):.3g} (delta_r = {self.delta_r:g}); "
                + ", ".join(f"{kind} k GUF {a:.3f} vs MCM {b:.3f}" for kind, (a, b) in self.k.items()))


@dataclass
class MultiResult:
    """The Monte Carlo result for several outputs (JCGM 102 7): the joint trial values and what 7.5-7.7 make of them.

    ``samples``: (outputs, M) magnitudes, one row per output in the order of ``names``, trial order (row j in
    ``units[j]``); ``outputs[name]``: the univariate :class:`Result` of each output (its own copy of its values, its
    own GUF and budget); ``covariance`` and ``correlation``: numpy arrays in the order of ``names``, the covariance
    in the outputs' units (entry (i, j) in units[i] units[j]); ``gum``: the :class:`MultiGUF`.
    """

    names: list
    units: list
    samples: np.ndarray
    coverage: float
    gum: MultiGUF
    outputs: dict
    ndig: int = 2
    batches: list = field(default_factory=list)

    @property
    def trials(self) -> int:
        return int(self.samples.shape[1])

    @property
    def estimate(self) -> np.ndarray:
        return self.samples.mean(axis=1)

    @property
    def covariance(self) -> np.ndarray:
        return np.atleast_2d(np.cov(self.samples, ddof=1))

    @property
    def correlation(self) -> np.ndarray:
        return _correlation_of(self.covariance)

    @property
    def std_uncertainty(self) -> np.ndarray:
        return np.sqrt(np.diagonal(self.covariance))

    def __repr__(self) -> str:
        u = ", ".join(f"u({n}) = {s:.2g} {un:~P}" for n, s, un in zip(self.names, self.std_uncertainty, self.units))
        return (f"<mtbudget MCM result for {len(self.names)} outputs ({', '.join(self.names)}): {u} (standard "
                f"uncertainties, k = 1); M = {self.trials} trials (JCGM 102)>")

    def region(self, kind: str = "hyperellipsoidal", coverage: float | None = None) -> CoverageRegion:
        """JCGM 102 7.7: the smallest region of the given shape, centred on the MCM estimate and scaled by its
        covariance, that holds the fraction p of the trials (the q-th smallest scaled distance, q as JCGM 101 7.7.1)."""
        from .stats import interval_indices

        p = self.coverage if coverage is None else coverage
        y, V = self.estimate, self.covariance
        D = self.samples - y[:, None]  # (m, M)
        if kind == "hyperellipsoidal":
            t = np.sqrt(np.einsum("im,im->m", np.linalg.solve(V, D), D))
            how = "MCM: the q-th smallest Mahalanobis distance of the trials (JCGM 102 7.7.2)"
        elif kind == "hyperrectangular":
            t = np.max(np.abs(D) / np.sqrt(np.diagonal(V))[:, None], axis=0)
            how = "MCM: the q-th smallest largest standardised deviation of the trials (JCGM 102 7.7.3)"
        else:
            raise ValueError(f"region kind must be 'hyperellipsoidal' or 'hyperrectangular', got {kind!r}")
        _, q = interval_indices(t.size, p)
        k = float(np.partition(t, q - 1)[q - 1])
        return CoverageRegion(kind, list(self.names), list(self.units), y, V, k, p, how)

    def validate(self, ndig: int | None = None) -> MultiValidation:
        """JCGM 102 clause 8 (see :class:`MultiValidation`)."""
        nd = self.ndig if ndig is None else ndig
        per = {n: self.outputs[n].validate(ndig=nd) for n in self.names}
        dr = np.abs(self.gum.correlation - self.correlation)
        delta_r = 0.5 * 10.0 ** (-nd)
        k = {kind: (self.gum.region(kind).k, self.region(kind).k) for kind in ("hyperellipsoidal", "hyperrectangular")}
        ok = all(v.passed for v in per.values()) and bool(np.all(dr <= delta_r))
        return MultiValidation(per, dr, delta_r, k, ok)


def _propagate_multi(model, inputs, names, correlations, coverage, trials, ss, ndig, batch, max_trials) -> MultiResult:
    g = gum_multi(model, inputs, coverage, correlations)
    R = _correlation_matrix(inputs, names, correlations)
    outs = g.names
    m = len(outs)

    def run(n, child) -> np.ndarray:
        arrays = _sample_inputs(inputs, n, child, R, names)
        Y = np.empty((m, n))
        mags = [(k, q.magnitude, q.units) for k, q in arrays.items()]
        for s in range(0, n, EVAL_BLOCK):
            e = min(n, s + EVAL_BLOCK)
            part = arrays if e - s == n else {k: Q_(v[s:e], u) for k, v, u in mags}
            y = _evaluate(model, part, names)
            if not isinstance(y, dict) or list(y) != outs:
                raise ModelError(f"the model must return the same named outputs at every call ({', '.join(outs)}); "
                                 f"got {list(y) if isinstance(y, dict) else type(y).__name__}")
            for j, o in enumerate(outs):
                yo = y[o] if isinstance(y[o], pint.Quantity) else Q_(np.asarray(y[o], float))
                try:
                    v = np.asarray(yo.to(g.units[j]).magnitude, float)
                except pint.DimensionalityError:
                    raise ModelError(f"output {o!r} changed units between calls ({yo.units:~} vs {g.units[j]:~})") from None
                if v.shape != (e - s,) and v.size != 1:
                    raise ModelError(f"output {o!r}: the model must return one value per trial, shape ({e - s},); "
                                     f"got shape {v.shape}")
                Y[j, s:e] = v
        if not np.isfinite(Y).all():
            for j in range(m):
                _check_nan(Y[j], arrays)
        return Y

    batches = []
    if trials is not None:
        if int(trials) < 2:
            raise ModelError(f"trials must be >= 2, got {trials}")
        Y = run(int(trials), ss.spawn(1)[0])
    else:  # JCGM 102 7.8 / JCGM 101 7.9: every output's y, u and interval ends to their numerical tolerance
        h_size = batch or max(int(100 / (1 - coverage)), 10_000)
        parts, stop = [], AdaptiveStop(ndig)
        for child in iter(lambda: ss.spawn(1)[0], None):
            Yb = run(h_size, child)
            parts.append(Yb)
            stop.add([batch_row(Yb[j], coverage) for j in range(m)])
            allu = np.concatenate(parts, axis=1).std(axis=1, ddof=1)
            if stop.done(allu) or len(stop.batches) * h_size >= max_trials:
                break
        Y = np.concatenate(parts, axis=1)
        batches = [h_size * (i + 1) for i in range(len(stop.batches))]
    results = {o: Result(Y[j].copy(), g.units[j], coverage, g.outputs[o], g.budgets[o], ndig) for j, o in enumerate(outs)}
    return MultiResult(list(outs), list(g.units), Y, coverage, g, results, ndig, batches)
