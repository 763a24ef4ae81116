"""Bootstrap confidence intervals and paired comparisons over a cell's samples.

What is resampled is the *sample* (one reference sweep and its future sweeps), never the
sweep: the future sweeps of one sample share its past and its scene, so their errors are
correlated and treating them as independent makes intervals too narrow. Optionally the unit
is a whole sequence, or a block of consecutive samples of one sequence (neighbouring samples
overlap in time).

The statistic is the leaderboard's flat mean over (sample, future sweep) with skipped (NaN)
sweeps left out: for a resample that draws unit ``u`` ``w_u`` times it is
``sum_u w_u S_u / sum_u w_u C_u`` where ``S_u`` is the sum of the unit's finite values and
``C_u`` their count. With every weight 1 this is exactly the point estimate.

Intervals are percentile intervals (numpy's linear interpolation between order statistics)
of ``resamples`` replicates. A paired comparison resamples the samples two cells share with
the same draws for both, and gives the difference of means, its interval, the relative
change and a two-sided bootstrap p-value,
``p = min(1, 2 min(1 + #{d* <= 0}, 1 + #{d* >= 0}) / (B + 1))`` over the ``B`` replicates
``d*`` of the difference. Draws come from ``numpy.random.default_rng((seed, units))``, so
the same store gives the same intervals on every run and machine. docs/reports.md says more.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
import pandas as pd

from pcfbench.errors import PcfbenchError

DEFAULT_RESAMPLES = 2000
DEFAULT_CONFIDENCE = 0.95
DEFAULT_SEED = 17
UNITS = ("sample", "sequence", "block")
#: Fewer resampling units than this: the interval is not computed (it would be 0-wide or near it).
MIN_UNITS = 2


@dataclass(frozen=True)
class Resampling:
    """How intervals are computed: the unit resampled, how often, at what confidence, the seed.

    ``unit`` is ``"sample"``, ``"sequence"`` (a whole sequence is one unit) or ``"block"``
    (``block`` consecutive samples of one sequence, in reference-sweep order, are one unit).
    """

    unit: str = "sample"
    block: int = 1
    resamples: int = DEFAULT_RESAMPLES
    confidence: float = DEFAULT_CONFIDENCE
    seed: int = DEFAULT_SEED

    def __post_init__(self) -> None:
        if self.unit not in UNITS:
            raise PcfbenchError(f"resampling unit {self.unit!r} is not one of {', '.join(UNITS)} (block:N for blocks of N samples)")
        if not isinstance(self.block, int) or self.block < 1:
            raise PcfbenchError(f"resampling block length must be an integer >= 1, got {self.block!r}")
        if not isinstance(self.resamples, int) or self.resamples < 100:
            raise PcfbenchError(f"bootstrap resamples must be an integer >= 100, got {self.resamples!r}")
        if not (0.5 <= self.confidence < 1):
            raise PcfbenchError(f"confidence must be in [0.5, 1), got {self.confidence!r}")

    @classmethod
    def parse(cls, text: str, **kwargs) -> "Resampling":
        """``sample``, ``sequence`` or ``block:N``."""
        unit, sep, n = text.partition(":")
        if unit == "block":
            if not sep or not n.isdigit() or int(n) < 1:
                raise PcfbenchError(f"resampling {text!r}: write block:N with N >= 1 consecutive samples per block")
            return cls("block", int(n), **kwargs)
        if sep or unit not in UNITS:
            raise PcfbenchError(f"resampling {text!r} is not one of sample, sequence, block:N")
        return cls(unit, **kwargs)

    def describe(self) -> str:
        what = {"sample": "samples", "sequence": "whole sequences",
                "block": f"blocks of {self.block} consecutive samples within a sequence"}[self.unit]
        return (f"{100 * self.confidence:g} % percentile bootstrap over {what}, "
                f"{self.resamples} resamples, seed {self.seed}")


@dataclass(frozen=True)
class SampleSums:
    """Per-sample sums and counts of the finite values of each metric, in a stable order.

    Rows are sorted by (sequence, reference index, sample id); ``sums`` and ``counts`` are
    (samples, metrics) float64.
    """

    sample_ids: np.ndarray
    sequences: np.ndarray
    ref_index: np.ndarray
    metrics: tuple[str, ...]
    sums: np.ndarray
    counts: np.ndarray

    def __len__(self) -> int:
        return len(self.sample_ids)

    @classmethod
    def of(cls, sample_ids, sequences, ref_index, metrics, sums, counts) -> "SampleSums":
        """Per-sample ``sums`` and ``counts`` (samples, metrics) given in any order, put in the
        stable order (sequence, reference index, sample id). A count need not be a number of
        values: the range figure's is each bin's rays, so the mean is ray-weighted."""
        ids = np.asarray(sample_ids, dtype=object).astype(str)
        seq = np.asarray(sequences, dtype=object).astype(str)
        ref = np.asarray(ref_index, dtype=np.int64)
        if len(set(ids)) != len(ids):
            raise PcfbenchError("SampleSums.of: a sample id occurs twice; sum each sample's values first")
        order = np.lexsort((ids, ref, seq))
        return cls(ids[order].astype(object), seq[order].astype(object), ref[order], tuple(metrics),
                   np.asarray(sums, np.float64)[order], np.asarray(counts, np.float64)[order])

    def take(self, sample_ids) -> "SampleSums":
        """The rows of ``sample_ids`` (which must all be present), in this object's order."""
        keep = np.isin(self.sample_ids, np.asarray(list(sample_ids), dtype=object))
        return SampleSums(self.sample_ids[keep], self.sequences[keep], self.ref_index[keep], self.metrics,
                          self.sums[keep], self.counts[keep])


def in_sample_order(rows: pd.DataFrame) -> pd.DataFrame:
    """``rows`` sorted by (sample_id, step), stably, with a fresh index: every sum and mean
    taken over them then adds in one order, whatever order the chunks (or a pool's workers)
    wrote them in, so the same rows give bit-identical numbers."""
    keys = [k for k in ("sample_id", "step") if k in rows]
    if not len(rows) or not keys:
        return rows
    return rows.sort_values(keys, kind="stable").reset_index(drop=True)


def sample_sums(rows: pd.DataFrame, metrics) -> SampleSums:
    """Sum and count the finite values of ``metrics`` per sample of scored rows (status ok),
    adding in sample order (``in_sample_order``)."""
    metrics = tuple(metrics)
    rows = in_sample_order(rows)
    if not len(rows):
        empty = np.zeros((0, len(metrics)))
        return SampleSums(np.array([], dtype=object), np.array([], dtype=object), np.array([], dtype=np.int64),
                          metrics, empty, empty.copy())
    missing = [c for c in ("sample_id", "sequence", "ref_index") if c not in rows]
    if missing:
        raise PcfbenchError(f"store rows lack the column(s) {', '.join(missing)} the intervals need")
    values = np.column_stack([rows[m].to_numpy(dtype=np.float64) if m in rows else np.full(len(rows), np.nan)
                              for m in metrics]) if metrics else np.zeros((len(rows), 0))
    finite = np.isfinite(values)
    sid = rows["sample_id"].to_numpy(dtype=object).astype(str)
    seq = rows["sequence"].to_numpy(dtype=object).astype(str)
    ref = rows["ref_index"].to_numpy(dtype=np.int64)
    ids, first, inverse = np.unique(sid, return_index=True, return_inverse=True)
    order = np.lexsort((ids, ref[first], seq[first]))  # by sequence, then ref_index, then id
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    which = rank[inverse]
    n = len(ids)
    sums = np.zeros((n, len(metrics)))
    counts = np.zeros((n, len(metrics)))
    np.add.at(sums, which, np.where(finite, values, 0.0))
    np.add.at(counts, which, finite.astype(np.float64))
    return SampleSums(ids[order].astype(object), seq[first][order].astype(object), ref[first][order],
                      metrics, sums, counts)


def unit_index(ss: SampleSums, resampling: Resampling) -> tuple[np.ndarray, int]:
    """The resampling unit (0 .. U-1) of each sample of ``ss``, and U."""
    n = len(ss)
    if resampling.unit == "sample":
        return np.arange(n), n
    _, seq_code = np.unique(ss.sequences.astype(str), return_inverse=True)
    if resampling.unit == "sequence":
        return seq_code, int(seq_code.max()) + 1 if n else 0
    # ss is sorted by (sequence, ref_index): the k-th sample of a sequence is in block k // L
    start = np.r_[0, np.flatnonzero(np.diff(seq_code)) + 1]
    rank = np.arange(n) - np.repeat(start, np.diff(np.r_[start, n]))
    key = seq_code.astype(np.int64) * (n + 1) + rank // resampling.block
    _, code = np.unique(key, return_inverse=True)
    return code, int(code.max()) + 1 if n else 0


def unit_sums(ss: SampleSums, resampling: Resampling) -> tuple[np.ndarray, np.ndarray]:
    """(U, metrics) sums and counts of finite values per resampling unit."""
    code, u = unit_index(ss, resampling)
    S = np.zeros((u, len(ss.metrics)))
    C = np.zeros((u, len(ss.metrics)))
    np.add.at(S, code, ss.sums)
    np.add.at(C, code, ss.counts)
    return S, C


def resample_indices(units: int, resampling: Resampling) -> np.ndarray:
    """(resamples, units) unit indices drawn with replacement; fixed by the seed and ``units``."""
    rng = np.random.default_rng((resampling.seed, units))
    return rng.integers(0, units, size=(resampling.resamples, units))


def resample_weights(indices: np.ndarray) -> np.ndarray:
    """(B, U) float64: how many times each unit is drawn in each resample of ``indices``."""
    B, u = indices.shape
    flat = (indices + u * np.arange(B)[:, None]).ravel()
    return np.bincount(flat, minlength=B * u).reshape(B, u).astype(np.float64)


@lru_cache(maxsize=32)
def _weights(units: int, resampling: Resampling) -> np.ndarray:
    W = resample_weights(resample_indices(units, resampling))
    W.setflags(write=False)
    return W


def replicate_means(S: np.ndarray, C: np.ndarray, indices: np.ndarray | None = None,
                    weights: np.ndarray | None = None) -> np.ndarray:
    """(B, metrics) flat means of each resample; NaN where a resample has no finite value.

    The resamples are given as unit ``indices`` (B, U) or as their ``weights``
    (:func:`resample_weights`).
    """
    W = resample_weights(indices) if weights is None else weights
    num, den = W @ S, W @ C
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(den > 0, num / np.where(den > 0, den, 1.0), np.nan)


def percentile_interval(replicates: np.ndarray, confidence: float) -> tuple[np.ndarray, np.ndarray]:
    """Per-column percentile interval of (B, metrics) replicates, NaN replicates left out.

    A column with fewer than half its replicates finite gets NaN (no interval).
    """
    alpha = 1.0 - confidence
    lo = np.full(replicates.shape[1], np.nan)
    hi = np.full(replicates.shape[1], np.nan)
    finite = np.isfinite(replicates)
    full = finite.all(axis=0)
    if full.any():
        q = np.quantile(replicates[:, full], [alpha / 2, 1 - alpha / 2], axis=0)
        lo[full], hi[full] = q[0], q[1]
    for j in np.flatnonzero(~full & (finite.sum(axis=0) * 2 >= len(replicates))):
        lo[j], hi[j] = np.quantile(replicates[finite[:, j], j], [alpha / 2, 1 - alpha / 2])
    return lo, hi


@dataclass(frozen=True)
class Interval:
    """Per metric: the interval of the flat mean, and how many units were resampled."""

    lo: np.ndarray
    hi: np.ndarray
    units: int


def interval(ss: SampleSums, resampling: Resampling) -> Interval:
    """The bootstrap interval of every metric's flat mean over ``ss``'s samples."""
    S, C = unit_sums(ss, resampling)
    u = len(S)
    if u < MIN_UNITS:
        nan = np.full(len(ss.metrics), np.nan)
        return Interval(nan, nan.copy(), u)
    reps = replicate_means(S, C, weights=_weights(u, resampling))
    lo, hi = percentile_interval(reps, resampling.confidence)
    return Interval(lo, hi, u)


@dataclass(frozen=True)
class Comparison:
    """Per metric, a cell against the reference on their shared samples.

    ``mean`` and ``reference_mean`` are flat means over the shared samples; ``diff`` is
    their difference with its interval; ``relative`` = mean / reference_mean - 1; ``p`` the
    two-sided paired bootstrap p-value (NaN where undefined).
    """

    shared: int
    units: int
    mean: np.ndarray
    reference_mean: np.ndarray
    diff: np.ndarray
    diff_lo: np.ndarray
    diff_hi: np.ndarray
    relative: np.ndarray
    p: np.ndarray


def bootstrap_p(diff_replicates: np.ndarray) -> np.ndarray:
    """Two-sided p-value per column of (B, metrics) replicates of a difference (NaN left out)."""
    finite = np.isfinite(diff_replicates)
    b = finite.sum(axis=0)
    below = (finite & (diff_replicates <= 0)).sum(axis=0)
    above = (finite & (diff_replicates >= 0)).sum(axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        p = np.minimum(1.0, 2.0 * (1.0 + np.minimum(below, above)) / (b + 1.0))
    return np.where(b * 2 >= len(diff_replicates), p, np.nan)


def compare(cell: SampleSums, reference: SampleSums, resampling: Resampling) -> Comparison:
    """Paired comparison of ``cell`` with ``reference`` on the samples both scored."""
    if cell.metrics != reference.metrics:
        raise PcfbenchError(f"cannot compare cells scored with different metrics: {cell.metrics} vs {reference.metrics}")
    shared = np.intersect1d(cell.sample_ids.astype(str), reference.sample_ids.astype(str))
    a, r = cell.take(shared), reference.take(shared)
    if not np.array_equal(a.sample_ids, r.sample_ids):  # same ids, different (sequence, ref_index)
        raise PcfbenchError("the shared samples of two cells disagree on their sequence or reference index")
    Sa, Ca = unit_sums(a, resampling)
    Sr, Cr = unit_sums(r, resampling)
    m = len(cell.metrics)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = Sa.sum(axis=0) / Ca.sum(axis=0) if len(Sa) else np.full(m, np.nan)
        ref_mean = Sr.sum(axis=0) / Cr.sum(axis=0) if len(Sr) else np.full(m, np.nan)
        relative = mean / ref_mean - 1.0
    nan = np.full(m, np.nan)
    u = len(Sa)
    if u < MIN_UNITS:
        return Comparison(len(shared), u, mean, ref_mean, mean - ref_mean, nan, nan.copy(), relative, nan.copy())
    W = _weights(u, resampling)
    d = replicate_means(Sa, Ca, weights=W) - replicate_means(Sr, Cr, weights=W)
    lo, hi = percentile_interval(d, resampling.confidence)
    return Comparison(len(shared), u, mean, ref_mean, mean - ref_mean, lo, hi, relative, bootstrap_p(d))
