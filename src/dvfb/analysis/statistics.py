"""Statistics of the analyses, on numbers only (no files, no rollouts): Spearman's rank correlation
within return bins (``dvfb analyze-value``, paper Fig. 3b) and the state coverage of trajectories
(``dvfb analyze-exploration``, paper Fig. 2)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from scipy.stats import spearmanr

from dvfb.analysis.common import AnalysisError

NAN = float("nan")


def spearman(x: Sequence[float], y: Sequence[float]) -> float:
    """Spearman's rho of two sequences; NaN with fewer than 3 points or a constant sequence."""
    x, y = np.asarray(x, dtype=float), np.asarray(y, dtype=float)
    if x.shape != y.shape or x.ndim != 1:
        raise ValueError("spearman needs two 1-D sequences of the same length")
    if x.size < 3 or np.ptp(x) == 0 or np.ptp(y) == 0:
        return NAN
    return float(spearmanr(x, y).statistic)


def quantile_bins(returns: Sequence[float], bins: int) -> list[np.ndarray]:
    """Indices of ``bins`` equal-count groups of increasing return (quantile bins by rank).

    Ties are broken by position (a stable sort), so every trajectory is in exactly one bin and the
    bin sizes differ by at most one.
    """
    if bins < 1:
        raise ValueError("bins must be >= 1")
    order = np.argsort(np.asarray(returns, dtype=float), kind="stable")
    return [part for part in np.array_split(order, min(bins, max(len(order), 1))) if part.size]


def binned_spearman(values: Sequence[float], returns: Sequence[float], bins: int) -> list[dict]:
    """Spearman's rho within each return bin (lowest returns first)."""
    values, returns = np.asarray(values, dtype=float), np.asarray(returns, dtype=float)
    result = []
    for i, index in enumerate(quantile_bins(returns, bins)):
        result.append({"bin": i, "n": int(index.size), "return_min": float(returns[index].min()),
                       "return_max": float(returns[index].max()),
                       "spearman": spearman(values[index], returns[index])})
    return result


def coverage(points: np.ndarray, cell_size: float) -> int:
    """Distinct cells ``floor(p / cell_size)`` occupied by the rows of ``points`` (N, C)."""
    if not cell_size > 0:  # also NaN
        raise AnalysisError("the coverage cell size must be positive")
    points = np.asarray(points, dtype=float)
    if points.size == 0:
        return 0
    points = points.reshape(-1, points.shape[-1])
    cells = np.floor(points / cell_size).astype(np.int64)
    return int(np.unique(cells, axis=0).shape[0])
