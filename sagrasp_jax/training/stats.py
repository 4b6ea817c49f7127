"""Statistics across seeds of training runs (the studies in experiments/ use it): means with 95 % Student-t
intervals, paired t-tests against a reference variant, binomial rates, first crossings of success
levels and curve bands.  The distributions are SciPy's (``scipy.stats``; SciPy comes with jax), imported
on first use, so the SB3 worker of ``bench_vs_paper_stack`` (``first_reach`` only) needs NumPy alone.
"""

from __future__ import annotations

import math
import warnings
from typing import Any, Mapping, Sequence

import numpy as np


def t975(df: Any) -> Any:
    """Two-sided 95 % Student-t quantile t_{0.975, df} (``scipy.stats.t.ppf``; df may be an array)."""
    from scipy import stats as sps

    q = sps.t.ppf(0.975, df)
    return float(q) if np.ndim(q) == 0 else q


def mean_ci(values: Sequence[float | None]) -> dict[str, Any]:
    """Mean and 95 % t-interval across seeds (``None`` bounds with fewer than 2 values)."""
    vals = np.asarray([v for v in values if v is not None and math.isfinite(v)], float)
    if vals.size == 0:
        return {"mean": None, "ci95": [None, None], "n": 0}
    m = float(vals.mean())
    if vals.size < 2:
        return {"mean": m, "ci95": [None, None], "n": 1}
    half = t975(vals.size - 1) * float(vals.std(ddof=1)) / math.sqrt(vals.size)
    return {"mean": m, "ci95": [m - half, m + half], "n": int(vals.size)}


def summarise(per_seed: list[dict[str, Any]]) -> dict[str, Any]:
    """``mean_ci`` of every metric of the per-seed rows (``seed`` aside)."""
    keys = [k for k in per_seed[0] if k != "seed"] if per_seed else []
    return {k: mean_ci([p.get(k) for p in per_seed]) for k in keys}


def t_test_p(t: float, df: int) -> float:
    """Two-sided p of Student's t with ``df`` degrees of freedom (``scipy.stats.t.sf``)."""
    from scipy import stats as sps

    if not math.isfinite(t):
        return 0.0
    return float(2.0 * sps.t.sf(abs(t), df))


def rate_at_least(p: float, n: int, level: float) -> float:
    """P(successes / n ≥ level) for n episodes of true success rate p (binomial; ``scipy.stats.binom``):
    how likely one seed's measured rate clears a target when its true rate is p."""
    from scipy import stats as sps

    k = math.ceil(level * n - 1e-9)  # the fewest successes that reach the level
    return float(sps.binom.sf(k - 1, n, p))


def paired(a: Sequence[float | None], b: Sequence[float | None], larger_is_better: bool = True) -> dict[str, Any]:
    """Paired comparison of ``a`` − ``b`` over the seeds where both have a value: mean difference,
    95 % t-interval, paired t-test two-sided p (``scipy.stats.ttest_rel``), and how many seeds ``a``
    wins / ties / loses."""
    pairs = [(x, y) for x, y in zip(a, b) if x is not None and y is not None and math.isfinite(x) and math.isfinite(y)]
    diffs = [x - y for x, y in pairs]
    out: dict[str, Any] = {"n": len(diffs), "mean_diff": None, "ci95": [None, None], "t": None, "p": None,
                           "wins": 0, "ties": 0, "losses": 0}
    if not diffs:
        return out
    sign = 1.0 if larger_is_better else -1.0
    out["wins"] = sum(sign * d > 0 for d in diffs)
    out["ties"] = sum(d == 0 for d in diffs)
    out["losses"] = sum(sign * d < 0 for d in diffs)
    n = len(diffs)
    mean = sum(diffs) / n
    out["mean_diff"] = mean
    if n < 2:
        return out
    sd = math.sqrt(sum((d - mean) ** 2 for d in diffs) / (n - 1))
    half = t975(n - 1) * sd / math.sqrt(n)
    out["ci95"] = [mean - half, mean + half]
    if sd == 0.0:
        out["p"] = 1.0 if mean == 0.0 else 0.0  # every seed the same difference: t is infinite (not JSON), p 0
    else:
        from scipy import stats as sps

        test = sps.ttest_rel([x for x, _ in pairs], [y for _, y in pairs])
        out["t"], out["p"] = float(test.statistic), float(test.pvalue)
    return out


def compare_with_reference(per_seed: Mapping[str, list[dict[str, Any]]], reference: str,
                           keys: Sequence[tuple[str, bool]]) -> dict[str, Any]:
    """Every variant minus ``reference``, seed by seed over the seeds both have: ``paired`` for each
    (metric, larger is better) of ``keys``."""
    if reference not in per_seed:
        return {}
    ref = {p["seed"]: p for p in per_seed[reference]}
    out: dict[str, Any] = {}
    for name, rows in per_seed.items():
        if name == reference:
            continue
        mine = {p["seed"]: p for p in rows}
        seeds = sorted(set(ref) & set(mine))
        out[name] = {key: paired([mine[s].get(key) for s in seeds], [ref[s].get(key) for s in seeds], better)
                     for key, better in keys}
        out[name]["seeds"] = seeds
    return out


def cell(stat: dict[str, Any], digits: int = 1) -> str:
    """``mean [lo, hi]`` of a ``mean_ci`` (``-`` without values)."""
    if stat["mean"] is None:
        return "-"
    lo, hi = stat["ci95"]
    return f"{stat['mean']:.{digits}f}" + ("" if lo is None else f" [{lo:.{digits}f}, {hi:.{digits}f}]")


# ---------------------------------------------------------------------- curves across seeds

def first_reach(points: list[tuple[float, int, float]], levels: Sequence[float]) -> dict[str, Any]:
    """For each level, the first (time_s, env_steps) whose success rate ≥ level, else 'not reached in budget'."""
    out: dict[str, Any] = {}
    for level in levels:
        hit = next(((t, s) for t, s, v in points if v >= level), None)
        out[f"{level:g}"] = ({"time_s": hit[0], "env_steps": hit[1]} if hit is not None
                             else "not reached in budget")
    return out


def curve_matrix(runs: list[list[dict[str, Any]]], key: str) -> tuple[np.ndarray, np.ndarray]:
    """(env_steps, values[seed, step]) on the env-step grid shared by all seeds; NaN where missing."""
    grids = [{int(r["env_steps"]): r.get(key) for r in rows if r.get(key) is not None} for rows in runs]
    common = sorted(set().union(*[set(g) for g in grids])) if grids else []
    x = np.asarray(common, float)
    y = np.full((len(grids), len(common)), np.nan)
    for i, g in enumerate(grids):
        for j, step in enumerate(common):
            if step in g:
                y[i, j] = float(g[step])
    return x, y


def band(y: np.ndarray, kind: str = "t95") -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mean across seeds and a band at every point: ``t95`` (95 % Student-t interval of the mean) or
    ``minmax`` (range of the seeds); the band collapses to the mean where only one seed has a value."""
    n = np.sum(np.isfinite(y), axis=0)
    if y.size == 0:
        return np.zeros(0), np.zeros(0), np.zeros(0)
    with np.errstate(invalid="ignore", divide="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN columns
        mean = np.nanmean(y, axis=0)
        if kind == "minmax":
            return mean, np.nanmin(y, axis=0), np.nanmax(y, axis=0)
        sd = np.nanstd(y, axis=0, ddof=1) if y.shape[0] > 1 else np.zeros_like(mean)
        t = np.where(n > 1, t975(np.maximum(n - 1, 1)), 0.0)
        half = np.where(n > 1, t * sd / np.sqrt(np.maximum(n, 1)), 0.0)
    return mean, mean - half, mean + half


def band_kind(requested: str, n_seeds: int) -> str:
    """``auto``: the t-interval from 3 seeds on; with 2 (t = 12.7) it says nothing, so the seeds' range."""
    if requested != "auto":
        return requested
    return "t95" if n_seeds >= 3 else "minmax"


BAND_LABELS = {"t95": "95 % t-band across seeds", "minmax": "band: range of the seeds"}
