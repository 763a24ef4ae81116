"""The metric contract and the per-sweep context metrics share their work through."""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from typing import Callable

import numpy as np

from pcfbench.data import Forecast, GroundTruth, RayQuery, Sample
from pcfbench.errors import PcfbenchError
from pcfbench.execution import ExecutionContext, current, in_pool_worker
from pcfbench.kinds import Better, Needs, parse
from pcfbench.metrics.rays import clamp_rays, lift, ray_errors as kept_ray_errors
from pcfbench.metrics.nn import (Index, angles_4docc, angles_az_el, masked_min_sq_dist, nearest_angles,
                                 submit_nearest_angles, submit_query)
from pcfbench.protocol import MIN_RANGE_M, ROI, Protocol
from pcfbench.boxes import Box


#: the shared searches a metric may declare (``Metric.searches``)
NN = "nn"
ANGLES = "angles"


@dataclass(frozen=True)
class Metric:
    """A per-(sample, future sweep) metric.

    ``fn(ctx)`` returns a float, or NaN when the sweep is skipped under the metric's empty
    policy (skipped sweeps are counted, never averaged). ``version`` changes whenever what
    the metric computes changes.

    ``higher_is_better`` has no default: every metric says which way it improves (False for
    an error such as a distance, True for a score such as an IoU), and the tables rank, bold
    and draw arrows from it. A default would rank a forgotten score backwards without a word,
    so a metric built without it is refused (:class:`~pcfbench.errors.PcfbenchError`).
    """

    name: str
    version: str
    fn: Callable[["SweepContext"], float]
    description: str
    reference: str = ""
    unit: str = ""
    empty_policy: str = ""
    #: what the forecast must carry for this metric (a :class:`~pcfbench.kinds.Needs`; the
    #: strings "points", "depths" and "either" are accepted)
    needs: Needs = Needs.EITHER
    #: True: a larger value is better (a score); False: a smaller one is (an error). Required.
    higher_is_better: bool = None  # type: ignore[assignment] - None is refused in __post_init__
    #: the context's shared searches the metric reads (``NN``: the k-d tree passes each way,
    #: ``ANGLES``: the angle-space searches): score_sample starts those of a suite together on the
    #: run's threads before the metrics run. Undeclared, a search runs when first asked for.
    searches: frozenset = frozenset()

    def __post_init__(self) -> None:
        if not isinstance(self.higher_is_better, bool):
            raise PcfbenchError(
                f"metric {self.name!r} must say which way is better: higher_is_better=False for an error "
                f"(lower is better, like every built-in metric) or True for a score; got {self.higher_is_better!r}"
            )
        object.__setattr__(self, "needs", parse(Needs, self.needs, f"metric {self.name!r}: needs"))
        unknown = set(self.searches) - {NN, ANGLES}
        if unknown:
            raise PcfbenchError(f"metric {self.name!r}: searches must be among {NN!r} and {ANGLES!r}, not {sorted(unknown)}")
        object.__setattr__(self, "searches", frozenset(self.searches))

    @property
    def better(self) -> Better:
        """``Better.HIGHER`` or ``Better.LOWER``, from ``higher_is_better``."""
        return Better.of(self.higher_is_better)

    def __call__(self, ctx: "SweepContext") -> float:
        return float(self.fn(ctx))


class SweepTruth:
    """The ground-truth side of one future sweep: what every forecast of the sweep is scored
    against, computed once and shared by every method scored on the sample (the runner's
    shared pass) and by the metrics of one forecast.

    Cached properties, each a pure function of the ground truth, the query origin, the ROI and
    the minimum range, so a shared one is the value a fresh context would compute, bit for bit.
    """

    def __init__(self, gt_points: np.ndarray, query: RayQuery, roi: Box = ROI, min_range_m: float = MIN_RANGE_M) -> None:
        self.gt_points = gt_points  # (M, 3) float32, reference frame
        self.query = query
        self.origin = np.asarray(query.origin_ref, dtype=np.float64)
        self.roi = roi
        self.min_range_m = min_range_m

    @cached_property
    def _lifted(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(gt64, gt_rel, gt_ranges, gt_in_roi) in one pass (pcfbench.metrics.rays.lift)."""
        return lift(self.gt_points, self.origin, *_bounds(self.roi))

    @cached_property
    def gt64(self) -> np.ndarray:
        """The ground truth as C-ordered float64."""
        return self._lifted[0]

    @cached_property
    def gt_in_roi(self) -> np.ndarray:
        return self._lifted[3]

    @cached_property
    def gt_roi(self) -> np.ndarray:
        return self.gt_points[self.gt_in_roi]

    @cached_property
    def gt_index(self) -> Index:
        return Index(self.gt64)

    @cached_property
    def gt_roi_index(self) -> Index:
        """A k-d tree on the ground truth's ROI crop (needs a non-empty crop)."""
        return Index(self.gt64[self.gt_in_roi])

    @cached_property
    def gt_rel(self) -> np.ndarray:
        """The ground truth relative to the sweep origin, (M, 3) float64."""
        return self._lifted[1]

    @cached_property
    def gt_ranges(self) -> np.ndarray:
        """(M,) float64 distance of each ground-truth point from the sweep origin."""
        return self._lifted[2]

    @cached_property
    def gt_angles(self) -> tuple[np.ndarray, np.ndarray]:
        """The ground-truth rays in both angle spaces: (4D-Occ, (azimuth, elevation)), (M, 2) float64."""
        return angles_4docc(self.gt_rel), angles_az_el(self.gt_rel)

    @cached_property
    def _clamps(self) -> tuple[np.ndarray, ...]:
        """(t_enter, t_exit, meets, gt_clamped, ray_kept) in one pass (pcfbench.metrics.rays.clamp_rays:
        the values of ``pcfbench.boxes.ray_box_interval`` on the unit rays and of the clip after it)."""
        return clamp_rays(self.gt_rel, self.gt_ranges, self.origin, *_bounds(self.roi), float(self.min_range_m))

    @cached_property
    def ray_clamp(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Per ground-truth ray: (t_enter, t_exit, meets_box) of the ROI along the unit ray o -> g."""
        return self._clamps[:3]

    @cached_property
    def gt_clamped(self) -> np.ndarray:
        """Clamped ground-truth range along each ray (where the ray leaves the ROI at most)."""
        return self._clamps[3]

    @cached_property
    def ray_kept(self) -> np.ndarray:
        """Rays that meet the ROI and whose clamped ground-truth range exceeds 1 cm."""
        return self._clamps[4]

    def kept_range_groups(self, width: float) -> list[tuple[int, np.ndarray]]:
        """The kept rays (``ray_kept``, in their order) in bins of ``width`` metres of ground-truth
        range: per bin k ([k width, (k + 1) width)), ascending, the positions among the kept rays
        that fall in it, ascending (so ``x[positions]`` is ``x[bin == k]``, element for element).
        Computed once per width (the store's range bins, ``pcfbench.store.ranges``)."""
        groups = self.__dict__.setdefault("_range_groups", {})
        if width not in groups:
            b = np.floor(self.gt_ranges[self.ray_kept] / width).astype(np.int64)
            order = np.argsort(b, kind="stable")
            bins, starts = np.unique(b[order], return_index=True)
            ends = [*starts[1:].tolist(), len(b)]
            groups[width] = [(int(k), order[s:e]) for k, s, e in zip(bins, starts.tolist(), ends)]
        return groups[width]


def _bounds(box: Box) -> tuple[np.ndarray, np.ndarray]:
    """(lo, hi) float64 of a box, for the kernels of pcfbench.metrics.rays."""
    return np.asarray(box.lo, dtype=np.float64), np.asarray(box.hi, dtype=np.float64)


def _truth_property(name: str, doc: str | None = None) -> property:
    return property(lambda self: getattr(self.truth, name), doc=doc or f"``SweepTruth.{name}`` of the context's truth.")


class SweepContext:
    """One future sweep to score: prediction, ground truth and the query rays, reference frame.

    Derived quantities (crops, nearest-neighbour passes, clamped ranges, per-ray predicted
    depths) are cached properties, so a suite of metrics pays for each only once: one exact
    nearest-neighbour pass each way serves CD and, re-querying only the few points whose
    neighbour lies outside the ROI, NFCD; one angular nearest-neighbour pass per angle space
    serves L1 and AbsRel.
    """

    def __init__(
        self,
        gt_points: np.ndarray,
        query: RayQuery,
        pred_points: np.ndarray | None,
        pred_depths: np.ndarray | None,
        roi: Box = ROI,
        execution: ExecutionContext | None = None,
        min_range_m: float = MIN_RANGE_M,
        truth: SweepTruth | None = None,
    ) -> None:
        # the ground-truth side (``truth``: one shared with other forecasts of this sweep, made
        # for the same points, query, ROI and minimum range)
        if truth is None:
            truth = SweepTruth(gt_points, query, roi, min_range_m)
        elif truth.gt_points is not gt_points or truth.query is not query or truth.roi != roi \
                or truth.min_range_m != min_range_m:
            raise ValueError("SweepContext: the shared truth was made for another sweep, ROI or minimum range")
        self.truth = truth
        self.gt_points = gt_points  # (M, 3) float32, reference frame
        self.query = query
        self.origin = truth.origin
        self.pred_depths = pred_depths  # (M,) or None
        self._pred_points = pred_points  # (K, 3) or None
        self.roi = roi  # the protocol's region of interest (the caller's protocol; default: the active one)
        self.min_range_m = min_range_m  # the protocol's minimum range (m)
        self.execution = execution  # thread budget of the shared searches; None: the process's

    gt64 = _truth_property("gt64")
    gt_in_roi = _truth_property("gt_in_roi")
    gt_roi = _truth_property("gt_roi")
    gt_index = _truth_property("gt_index")
    gt_rel = _truth_property("gt_rel")
    gt_ranges = _truth_property("gt_ranges", "(M,) float64 distance of each ground-truth point from the sweep origin.")
    ray_clamp = _truth_property("ray_clamp", "Per ground-truth ray: (t_enter, t_exit, meets_box) of the ROI along o -> g.")
    gt_clamped = _truth_property("gt_clamped", "Clamped ground-truth range along each ray.")
    ray_kept = _truth_property("ray_kept", "Rays that meet the ROI and whose clamped ground-truth range exceeds 1 cm.")

    # -- points ----------------------------------------------------------------------------
    @cached_property
    def pred_points(self) -> np.ndarray:
        """Predicted points; from depths along the query rays when only depths were given."""
        if self._pred_points is not None:
            return self._pred_points
        d = self.pred_depths.astype(np.float64)[:, None]
        return (self.origin + self.query.directions_ref.astype(np.float64) * d).astype(np.float32)

    @cached_property
    def _pred_lifted(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(pred64, pred_rel, pred_ranges, pred_in_roi) in one pass (pcfbench.metrics.rays.lift)."""
        return lift(self.pred_points, self.origin, *_bounds(self.roi))

    @cached_property
    def pred64(self) -> np.ndarray:
        return self._pred_lifted[0]

    @cached_property
    def pred_in_roi(self) -> np.ndarray:
        return self._pred_lifted[3]

    @cached_property
    def pred_roi(self) -> np.ndarray:
        return self.pred_points[self.pred_in_roi]

    # -- nearest neighbours in 3D (Chamfer) --------------------------------------------------
    @cached_property
    def pred_index(self) -> Index:
        return Index(self.pred64)

    @cached_property
    def nn_pred_to_gt(self) -> tuple[np.ndarray, np.ndarray]:
        """(squared distance, index into gt) for every predicted point; needs both non-empty."""
        return self.gt_index.query(self.pred64)

    @cached_property
    def nn_gt_to_pred(self) -> tuple[np.ndarray, np.ndarray]:
        return self.pred_index.query(self.gt64)

    def _cropped_nn(self, full: tuple[np.ndarray, np.ndarray], q_in: np.ndarray, t_in: np.ndarray,
                    queries: np.ndarray, index: Index) -> np.ndarray:
        """Squared NN distances from the cropped queries to the cropped targets.

        A cropped query whose nearest neighbour in the whole target set lies inside the ROI
        has the same nearest distance within the crop; only the others are asked again
        (brute force over the in-ROI targets when they are few, else a tree on the crop).
        """
        d2, idx = full[0][q_in], full[1][q_in]
        redo = np.flatnonzero(~t_in[idx])
        if redo.size:
            q = queries[np.flatnonzero(q_in)[redo]]
            if redo.size <= 32:  # a few points: brute force over the in-ROI targets
                d2[redo] = masked_min_sq_dist(q, index.points, t_in)
            elif index is self.gt_index:  # the ground truth's crop: a tree shared by every forecast
                d2[redo] = self.truth.gt_roi_index.query(q)[0]
            else:
                d2[redo] = Index(index.points[t_in]).query(q)[0]
        return d2

    @property
    def crops_hold_points(self) -> bool:
        """Whether both ROI crops (prediction and ground truth) hold a point: NFCD is defined."""
        return bool(self.pred_in_roi.any() and self.gt_in_roi.any())

    @cached_property
    def nn_pred_to_gt_roi(self) -> np.ndarray:
        """Squared NN distances from each cropped predicted point to the cropped ground truth."""
        return self._cropped_nn(self.nn_pred_to_gt, self.pred_in_roi, self.gt_in_roi, self.pred64, self.gt_index)

    @cached_property
    def nn_gt_to_pred_roi(self) -> np.ndarray:
        return self._cropped_nn(self.nn_gt_to_pred, self.gt_in_roi, self.pred_in_roi, self.gt64, self.pred_index)

    # -- rays (L1, AbsRel) ---------------------------------------------------------------------
    @cached_property
    def pred_rel(self) -> np.ndarray:
        return self._pred_lifted[1]

    @cached_property
    def pred_ranges(self) -> np.ndarray:
        return self._pred_lifted[2]

    @cached_property
    def _angular_nearest(self) -> tuple[np.ndarray, np.ndarray]:
        """Nearest predicted point per ground-truth ray in both angle spaces (4D-Occ, wrapped),
        the two exact searches shared out over the context's threads (pcfbench.metrics.nn.nearest_angles)."""
        known = self.truth.__dict__.get("gt_angles")  # shared; else made by the searches and kept
        execution = self.execution or current()
        if known is not None or execution.threads == 1 or in_pool_worker():
            return nearest_angles(self.pred_rel, self.gt_rel, execution, self.truth.gt_angles)
        done, queries = submit_nearest_angles(execution.pool(), self.pred_rel, self.gt_rel)
        return self._keep_angles(done, queries)

    def _keep_angles(self, done: list, queries: list) -> tuple[np.ndarray, np.ndarray]:
        out = done[0].result(), done[1].result()
        self.truth.__dict__.setdefault("gt_angles", (queries[0].result(), queries[1].result()))
        return out

    def share_out(self, searches: frozenset | set) -> None:
        """Start ``searches`` (``NN``, ``ANGLES``) together as jobs of the execution context's
        pool and wait for them: the k-d tree builds and the angle searches' grids first, then
        the tree passes and the grid passes in pieces, so that the threads share all of it
        (a search alone leaves threads idle while a tree or a grid is built). The answers are
        the cached ones a metric would make alone. One thread, in a pool worker, or an empty
        side: nothing to share, each search runs when a metric asks."""
        execution = self.execution or current()
        if execution.threads == 1 or in_pool_worker() or self.gt_points.shape[0] == 0:
            return
        if self._pred_points is not None and self._pred_points.shape[0] == 0:
            return
        pool = execution.pool()
        jobs = {}
        truth = self.truth
        if NN in searches and "nn_pred_to_gt" not in self.__dict__:
            gt_index = pool.submit(lambda: truth.gt_index)
            pred_index = pool.submit(lambda: self.pred_index)
            jobs["nn_pred_to_gt"] = submit_query(pool, gt_index.result, self.pred64)
            jobs["nn_gt_to_pred"] = submit_query(pool, pred_index.result, truth.gt64)
        angles = None
        if ANGLES in searches and self.pred_depths is None and "_angular_nearest" not in self.__dict__:
            angles = submit_nearest_angles(pool, self.pred_rel, truth.gt_rel, truth.__dict__.get("gt_angles"))
        # what the built-in metrics read beside the searches, queued after them: the threads take
        # it as they come free at the searches' end, instead of the calling thread after them
        prep = []
        if NN in searches:
            prep += [lambda: truth.gt_in_roi, lambda: self.pred_in_roi]
        if ANGLES in searches and self.pred_depths is None:
            prep += [lambda: truth.ray_kept, lambda: truth.gt_clamped, lambda: self.pred_ranges]
        prep = [pool.submit(job) for job in prep]
        # what the built-in metrics then compute from the searches' answers (the ROI crops' NN
        # distances, the per-ray errors and their medians), queued as each search's answers are
        # stored: the threads take it beside the searches' last pieces, instead of the calling
        # thread alone after them
        after = []
        for name, job in jobs.items():
            self.__dict__[name] = job.result()
        if jobs:  # (the crops' passes only when both crops hold points, as the metrics ask for them)
            after += [pool.submit(lambda: self.crops_hold_points and self.nn_pred_to_gt_roi),
                      pool.submit(lambda: self.crops_hold_points and self.nn_gt_to_pred_roi)]
        if angles is not None:
            self.__dict__["_angular_nearest"] = self._keep_angles(*angles)
            after += [pool.submit(lambda: self.ray_errors_4docc), pool.submit(lambda: self.ray_error_medians)]
        for job in prep + after:
            job.result()

    def _ray_depth(self, which: int) -> np.ndarray | None:
        if self.pred_depths is not None:
            return self.pred_depths.astype(np.float64)
        if self.pred_points.shape[0] == 0:
            return None
        return self.pred_ranges[self._angular_nearest[which]]

    @cached_property
    def ray_depth_4docc(self) -> np.ndarray | None:
        """Predicted depth per ground-truth ray: the forecast's depths, or the range of the
        predicted point nearest in the 4D-Occ angle space; None for an empty prediction."""
        return self._ray_depth(0)

    @cached_property
    def ray_depth(self) -> np.ndarray | None:
        """As ray_depth_4docc, nearest in (azimuth, elevation) with azimuth wrap-around."""
        return self._ray_depth(1)

    def ray_errors(self, depth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(|g_c - p_c|, |g_c - p_c| / |g_c - o_c|) on the kept rays, for per-ray predicted depths."""
        t_enter, t_exit, _ = self.ray_clamp
        return kept_ray_errors(np.ascontiguousarray(depth, dtype=np.float64), t_enter, t_exit, self.gt_clamped,
                               self.ray_kept)

    @cached_property
    def ray_errors_4docc(self) -> tuple[np.ndarray, np.ndarray] | None:
        d = self.ray_depth_4docc
        return None if d is None else self.ray_errors(d)

    @cached_property
    def ray_errors_wrapped(self) -> tuple[np.ndarray, np.ndarray] | None:
        d = self.ray_depth
        return None if d is None else self.ray_errors(d)

    @cached_property
    def ray_error_medians(self) -> tuple[float, float] | None:
        """(median L1 error, median AbsRel) of ``ray_errors_wrapped``; None without a predicted
        depth, NaN without a kept ray."""
        errs = self.ray_errors_wrapped
        if errs is None:
            return None
        return tuple(float(np.median(e)) if e.size else float("nan") for e in errs)


def score_sample(
    sample: Sample, truth: GroundTruth, forecast: Forecast, metrics: list[Metric],
    execution: ExecutionContext | None = None,
    on_sweep: Callable[[dict, "SweepContext"], None] | None = None,
    protocol: Protocol | None = None,
    truths: list[SweepTruth] | None = None,
    context_cls: type["SweepContext"] | None = None,
) -> list[dict[str, float | int]]:
    """Score every future sweep of a validated forecast: one row per sweep with every metric.

    ``truths``: the sample's :func:`sweep_truths`, when several forecasts of the sample are
    scored (the runner's shared pass builds the ground truth's structures once); the rows are
    the same with or without. ``context_cls``: the SweepContext class whose searches score it
    (pcfbench.metrics.backend: the numpy default or torch).

    ``protocol``: the one the sample was made under (its ROI and minimum range; the
    runner hands down its :class:`~pcfbench.protocol.SampleBuilder`'s); default: the active one.

    ``execution``: the thread budget of the metrics' shared searches (default: the
    process's); the rows do not depend on it. ``on_sweep(row, ctx)``: called with each
    sweep's row and context once it is scored (the runner's range bins reuse its work)."""
    truths = truths if truths is not None else sweep_truths(sample, truth, protocol)
    searches = frozenset().union(*(m.searches for m in metrics))
    rows = []
    for k, query in enumerate(sample.queries):
        gt = truth.future_points_ref[k]
        ctx = (context_cls or SweepContext)(
            gt_points=gt,
            query=query,
            pred_points=forecast.points_ref[k] if forecast.points_ref is not None else None,
            pred_depths=forecast.depths[k] if forecast.depths is not None else None,
            roi=truths[k].roi,
            execution=execution,
            min_range_m=truths[k].min_range_m,
            truth=truths[k],
        )
        if searches:
            ctx.share_out(searches)
        row: dict[str, float | int] = {"step": k, "n_gt": int(gt.shape[0]), "n_pred": int(ctx.pred_points.shape[0])}
        for metric in metrics:
            if gt.shape[0] == 0:
                row[metric.name] = float("nan")  # sweeps without ground truth are skipped
            elif metric.needs == Needs.DEPTHS and forecast.depths is None:
                row[metric.name] = float("nan")
            else:
                row[metric.name] = metric(ctx)
        if on_sweep is not None:
            on_sweep(row, ctx)
        rows.append(row)
    return rows


def sweep_truths(sample: Sample, truth: GroundTruth, protocol: Protocol | None = None) -> list[SweepTruth]:
    """One :class:`SweepTruth` per future sweep of ``sample``, under ``protocol``'s ROI and
    minimum range (default: the active protocol's), to share between the forecasts scored on it."""
    roi = protocol.roi if protocol is not None else ROI
    min_range_m = protocol.min_range_m if protocol is not None else MIN_RANGE_M
    return [SweepTruth(truth.future_points_ref[k], q, roi, min_range_m) for k, q in enumerate(sample.queries)]
