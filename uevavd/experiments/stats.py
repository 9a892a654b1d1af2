"""Statistics over runs for the ablation report: 95% confidence intervals, differences of
means, linear trends, and the sliding-window smoothing of learning curves.

With one recognizer, the units are independent RL seeds and an interval is a two-sided
Student-t interval over them (Welch for differences); with fewer than two seeds it is
undefined (NaN), which the claims turn into "cannot be judged".

With several recognizers (each trained with its own seed, with its own tables, and every RL
seed run on each), runs are nested: seeds within recognizers. Then an interval is a
two-stage percentile bootstrap (:func:`nested_bootstrap`): resample the recognizers with
replacement, then the seeds within each drawn recognizer, and take the mean of the
recognizer means; 95 % of :data:`BOOTSTRAP_SAMPLES` resamples. Every estimate draws the
recognizers with the same random stream, so two methods' bootstrap means are paired by
recognizer (their difference keeps the recognizer they share), and a percentile interval
never leaves the range of the values it resamples.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import pandas as pd
from scipy import stats as _st

#: Confidence level of every interval in the report.
LEVEL = 0.95
#: Resamples of the nested bootstrap, and the seed of its random stream.
BOOTSTRAP_SAMPLES = 4000
BOOTSTRAP_SEED = 20261124


@dataclass(frozen=True)
class Estimate:
    """Mean of ``n`` independent values with std (ddof=1) and a t-interval.

    ``lo``/``hi`` are NaN when ``n < 2`` (no spread can be estimated); ``std`` is NaN
    then too. For a deterministic reference (e.g. passive) build it with :meth:`exact`.
    """

    mean: float
    std: float
    n: int
    lo: float
    hi: float
    #: bootstrap means (nested over recognizers and seeds), when the estimate came from
    #: :func:`nested_bootstrap`; differences between two such estimates use them
    boot: np.ndarray | None = field(default=None, compare=False, repr=False)

    @classmethod
    def of(cls, values, level: float = LEVEL, *, groups=None) -> Estimate:
        """Estimate of the mean of ``values``; with ``groups`` (the recognizer of each value)
        holding two or more distinct groups, the nested bootstrap, else the t-interval."""
        if groups is not None and np.unique(np.asarray(groups)).size >= 2:
            return nested_bootstrap(values, groups, level)
        x = np.asarray(values, dtype=np.float64).ravel()
        x = x[np.isfinite(x)]
        n = int(x.size)
        if n == 0:
            return cls(math.nan, math.nan, 0, math.nan, math.nan)
        mean = float(x.mean())
        if n < 2:
            return cls(mean, math.nan, 1, math.nan, math.nan)
        std = float(x.std(ddof=1))
        half = float(_st.t.ppf(0.5 + level / 2, n - 1)) * std / math.sqrt(n)
        return cls(mean, std, n, mean - half, mean + half)

    @classmethod
    def exact(cls, value: float) -> Estimate:
        """A known constant: zero-width interval (used for deterministic baselines)."""
        v = float(value)
        return cls(v, 0.0, 1, v, v)

    @property
    def defined(self) -> bool:
        """True when the interval exists (at least two values, or an exact constant)."""
        return math.isfinite(self.lo) and math.isfinite(self.hi)

    def fmt(self, digits: int = 3, ci: bool = True) -> str:
        """``"m ± s [lo, hi]"`` (or ``"m (n=1)"`` when no spread exists)."""
        if self.n == 0:
            return "n/a"
        if not math.isfinite(self.std):
            return f"{self.mean:.{digits}f} (n=1)"
        s = f"{self.mean:.{digits}f} ± {self.std:.{digits}f}"
        if ci:
            s += f" [{self.lo:.{digits}f}, {self.hi:.{digits}f}]"
        return s


def nested_bootstrap(values, groups, level: float = LEVEL) -> Estimate:
    """Two-stage percentile bootstrap of the mean of ``values`` nested in ``groups``
    (recognizers): the point estimate is the mean of the group means; each resample draws
    the groups with replacement, then the values within each drawn group with replacement.
    ``std`` is the bootstrap standard error; ``boot`` holds the resampled means."""
    x = np.asarray(values, dtype=np.float64).ravel()
    g = np.asarray(groups).ravel()
    ok = np.isfinite(x)
    x, g = x[ok], g[ok]
    if x.size == 0:
        return Estimate(math.nan, math.nan, 0, math.nan, math.nan)
    labels = np.unique(g)
    members = [x[g == k] for k in labels]
    rng = np.random.default_rng(BOOTSTRAP_SEED)
    pick = rng.integers(0, len(labels), size=(BOOTSTRAP_SAMPLES, len(labels)))  # the same for every estimate
    inner = np.stack([m[rng.integers(0, m.size, size=(BOOTSTRAP_SAMPLES, m.size))].mean(1) for m in members])
    boot = inner[pick, np.arange(BOOTSTRAP_SAMPLES)[:, None]].mean(1)
    mean = float(np.mean([m.mean() for m in members]))
    lo, hi = np.quantile(boot, [0.5 - level / 2, 0.5 + level / 2])
    return Estimate(mean, float(boot.std(ddof=1)), int(x.size), float(lo), float(hi), boot)


def difference(a, b, level: float = LEVEL) -> Estimate:
    """Estimate of ``mean(a) - mean(b)`` for independent samples (Welch's t interval).

    ``a`` and ``b`` are 1-D arrays of per-seed values or :class:`Estimate`; an exact
    Estimate (std 0) contributes no variance, so comparing a method with a
    deterministic baseline reduces to the one-sample interval of the method.
    Returns an Estimate whose ``n`` is the smaller sample size and whose ``std`` is the
    standard error of the difference.
    """
    ea = a if isinstance(a, Estimate) else Estimate.of(a)
    eb = b if isinstance(b, Estimate) else Estimate.of(b)
    d = ea.mean - eb.mean
    n = min(ea.n, eb.n)
    if ea.n == 0 or eb.n == 0:
        return Estimate(math.nan, math.nan, 0, math.nan, math.nan)
    if ea.boot is not None or eb.boot is not None:  # nested bootstrap: paired by recognizer draws
        da = ea.boot if ea.boot is not None else np.full(BOOTSTRAP_SAMPLES, ea.mean)
        db = eb.boot if eb.boot is not None else np.full(BOOTSTRAP_SAMPLES, eb.mean)
        if (ea.boot is None and ea.std != 0.0) or (eb.boot is None and eb.std != 0.0):
            return Estimate(d, math.nan, n, math.nan, math.nan)  # one side nested, the other not: no interval
        boot = da - db
        lo, hi = np.quantile(boot, [0.5 - level / 2, 0.5 + level / 2])
        return Estimate(d, float(boot.std(ddof=1)), n, float(lo), float(hi), boot)
    parts = []  # (variance of the mean, degrees of freedom) of each side that varies
    for e in (ea, eb):
        if e.std == 0.0:
            continue
        if not math.isfinite(e.std):
            return Estimate(d, math.nan, n, math.nan, math.nan)
        parts.append((e.std**2 / e.n, e.n - 1))
    if not parts:
        return Estimate(d, 0.0, n, d, d)
    se2 = sum(v for v, _ in parts)
    if se2 == 0.0:
        return Estimate(d, 0.0, n, d, d)
    # Welch-Satterthwaite degrees of freedom
    df = se2**2 / sum(v**2 / k for v, k in parts)
    half = float(_st.t.ppf(0.5 + level / 2, df)) * math.sqrt(se2)
    return Estimate(d, math.sqrt(se2), n, d - half, d + half)


def slope(x, y, level: float = LEVEL) -> Estimate:
    """Least-squares slope of ``y`` on ``x`` with a t-interval (df = n - 2).

    ``x``, ``y``: 1-D float arrays of equal length, one point per (setting, seed).
    NaN interval when fewer than three points or fewer than two distinct x.
    """
    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    ok = np.isfinite(x) & np.isfinite(y)
    x, y = x[ok], y[ok]
    n = int(x.size)
    if n < 2 or np.unique(x).size < 2:
        return Estimate(math.nan, math.nan, n, math.nan, math.nan)
    xm = x - x.mean()
    sxx = float((xm**2).sum())
    b = float((xm * (y - y.mean())).sum() / sxx)
    if n < 3:
        return Estimate(b, math.nan, n, math.nan, math.nan)
    resid = y - y.mean() - b * xm
    se = math.sqrt(float((resid**2).sum()) / (n - 2) / sxx)
    half = float(_st.t.ppf(0.5 + level / 2, n - 2)) * se
    return Estimate(b, se, n, b - half, b + half)


def sign_verdict(e: Estimate, want: int) -> str | None:
    """``"agrees"`` if the whole interval lies on the ``want`` side of zero (+1 or -1),
    ``"disagrees"`` if it lies wholly on the other side, ``"cannot tell"`` if it covers
    zero, ``None`` if the interval is undefined."""
    if not e.defined:
        return None
    if want * e.lo > 0 and want * e.hi > 0:
        return "agrees"
    if want * e.lo < 0 and want * e.hi < 0:
        return "disagrees"
    return "cannot tell"


def smooth(values, window: int) -> np.ndarray:
    """Trailing sliding-window mean of a 1-D curve (``min_periods=1``, so the first
    points average what exists). ``window <= 1`` returns the curve unchanged."""
    s = pd.Series(np.asarray(values, dtype=np.float64))
    if window <= 1:
        return s.to_numpy()
    return s.rolling(int(window), min_periods=1).mean().to_numpy()
