"""The metrics' exact nearest-neighbour searches in torch, for a GPU (and the CPU, where CI tests it).

Brute force in chunks of queries: every query's distances to every point in float32 on the
device, its ``CANDIDATES`` nearest kept (``topk``), then the float64 recheck on the host: the
candidates' distances by the very formula of the CPU searches (pcfbench.metrics.nn for 3D,
pcfbench.nn2d for the angle spaces), the smallest taken, ties to the lowest index. The answer is
exact wherever the candidates surely hold every point at the smallest float64 distance: the
float32 distance of a point is within ``_slack`` of its exact one (the coordinates' rounding to
float32 and the arithmetic's, bounded generously), so a point left out is surely farther when
the last candidate's float32 distance exceeds the first's by twice that. A query where it does
not (many points nearly as near: ties, a lattice) is searched again over every point within
that slack of its best, each rechecked in float64.

Each distinct point is searched once (``pcfbench.metrics.nn.distinct``): a forecast with repeated
points would otherwise fill the candidates with copies of one point and send every query to
the slow path. The first of each set of equal points stands for it, so ties still go to the
lowest index.
"""

from __future__ import annotations

import numpy as np

from pcfbench.metrics.nn import TWO_PI, angles_4docc, angles_az_el, distinct

#: nearest candidates per query kept from the float32 pass
CANDIDATES = 8
#: bytes of float32 distances per chunk of queries (the chunk's rows x the points)
CHUNK_BYTES = 256 * 2**20
#: relative bound on float32 rounding of a distance computed from float32 coordinates (a few
#: units in the last place, taken 30x wider)
REL_SLACK = 1e-5
#: absolute bound on the float32 rounding of angles in [-pi, pi] (2^-24 pi each coordinate, both
#: points, the period's rounding; taken 5x wider)
ANGLE_SLACK = 4e-6


def default_device() -> str:
    """``"cuda"`` when torch sees a GPU, else ``"cpu"``."""
    import torch

    return "cuda" if torch.cuda.is_available() else "cpu"


class TorchSearch:
    """Exact nearest neighbours on ``device`` (a torch device name): 3D (Chamfer) and the two angle spaces."""

    def __init__(self, device: str | None = None) -> None:
        import torch

        self.torch = torch
        self.device = torch.device(device or default_device())

    # -- the float32 pass ----------------------------------------------------------------------
    def _candidates(self, queries: np.ndarray, points: np.ndarray, period: float = 0.0,
                    angle: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(candidates (Q, k) int64 into points, their float32 distances (Q, k), unsure (Q,) bool).

        Distances are Euclidean (not squared), float32; with ``period`` > 0 dimension 0 is periodic."""
        torch = self.torch
        q32 = torch.from_numpy(np.ascontiguousarray(queries, dtype=np.float32)).to(self.device)
        p32 = torch.from_numpy(np.ascontiguousarray(points, dtype=np.float32)).to(self.device)
        n, k = p32.shape[0], min(CANDIDATES, p32.shape[0])
        rows = max(1, CHUNK_BYTES // (4 * max(n, 1) * (2 if period > 0 else 1)))
        cand, dist = [], []
        for a in range(0, q32.shape[0], rows):
            d = self._distances(q32[a:a + rows], p32, period)
            v, i = torch.topk(d, k, dim=1, largest=False, sorted=True)
            cand.append(i.cpu())
            dist.append(v.cpu())
        if not cand:
            return np.zeros((0, k), np.int64), np.zeros((0, k), np.float32), np.zeros(0, bool)
        c = torch.cat(cand).numpy().astype(np.int64)
        v = torch.cat(dist).numpy().astype(np.float64)
        self._abs = ANGLE_SLACK if angle else _coordinate_slack(queries, points)
        slack = self._slack(v[:, 0])
        unsure = (v[:, -1] - v[:, 0] <= 2 * slack) if k < n else np.zeros(c.shape[0], bool)
        return c, v, unsure

    def _slack(self, best: np.ndarray) -> np.ndarray:
        return best * REL_SLACK + self._abs

    def _near_all(self, queries: np.ndarray, points: np.ndarray, which: np.ndarray, best: np.ndarray,
                  period: float) -> tuple[np.ndarray, np.ndarray]:
        """(row, point) pairs, rows into ``which`` in increasing order: every point within twice
        the slack of ``best`` (its float32 distance) for each of the queries ``which``."""
        torch = self.torch
        p32 = torch.from_numpy(np.ascontiguousarray(points, dtype=np.float32)).to(self.device)
        limit = torch.from_numpy((best[which] + 2 * self._slack(best[which])).astype(np.float32)).to(self.device)
        rows = max(1, CHUNK_BYTES // (4 * points.shape[0] * (2 if period > 0 else 1)))
        out_r, out_p = [], []
        for a in range(0, which.shape[0], rows):
            q = torch.from_numpy(np.ascontiguousarray(queries[which[a:a + rows]], dtype=np.float32)).to(self.device)
            d = self._distances(q, p32, period)
            r, c = torch.nonzero(d <= limit[a:a + rows, None], as_tuple=True)
            out_r.append((r + a).cpu().numpy())
            out_p.append(c.cpu().numpy())
        return np.concatenate(out_r).astype(np.int64), np.concatenate(out_p).astype(np.int64)

    def _distances(self, q, p32, period: float):
        """(rows, points) float32 distances on the device; dimension 0 periodic with ``period`` > 0."""
        torch = self.torch
        if period > 0:
            dx = (q[:, None, 0] - p32[None, :, 0]).abs_()
            dx = torch.minimum(dx, period - dx)
            dy = q[:, None, 1] - p32[None, :, 1]
            return (dx.mul_(dx)).add_(dy.mul_(dy)).sqrt_()
        return torch.cdist(q, p32, compute_mode="donot_use_mm_for_euclid_dist")

    # -- the float64 recheck -------------------------------------------------------------------
    def _nearest(self, queries64: np.ndarray, points64: np.ndarray, period: float, angle: bool,
                 d2_of) -> tuple[np.ndarray, np.ndarray]:
        """(float64 squared distance, index) of each query's nearest point, ``d2_of(q, p)`` the
        CPU search's formula on (Q, k, D) broadcast rows."""
        first = distinct(points64)
        pts = points64 if first is None else points64[first]
        if pts.shape[0] == 0:
            raise ValueError("nearest neighbours: no points to search")
        cand, v, unsure = self._candidates(queries64, pts, period, angle)
        d2 = d2_of(queries64[:, None, :], pts[cand])
        best = d2.min(axis=1)
        idx = np.where(d2 == best[:, None], cand, pts.shape[0]).min(axis=1)
        which = np.flatnonzero(unsure)
        if which.size:
            row, c = self._near_all(queries64, pts, which, v[:, 0], period)
            d = d2_of(queries64[which[row]], pts[c])
            starts = np.flatnonzero(np.r_[True, row[1:] != row[:-1]])  # every row has its own best at least
            low = np.minimum.reduceat(d, starts)
            at = d == np.repeat(low, np.diff(np.r_[starts, row.shape[0]]))
            best[which] = low
            idx[which] = np.minimum.reduceat(np.where(at, c, pts.shape[0]), starts)
        return best, (idx if first is None else first[idx])

    def nearest_3d(self, queries: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(squared distance float64, index int64) of each query's nearest point, as
        ``pcfbench.metrics.nn.Index(points).query(queries)``: distances summed (dx^2 + dz^2) + dy^2."""
        q = np.ascontiguousarray(queries, dtype=np.float64)
        if q.shape[0] == 0:
            return np.zeros(0), np.zeros(0, dtype=np.int64)
        return self._nearest(q, np.ascontiguousarray(points, dtype=np.float64), 0.0, False, _d2_3d)

    def nearest_2d(self, data: np.ndarray, queries: np.ndarray, period: float = 0.0) -> np.ndarray:
        """Index of each query's nearest data point in an angle space, as ``pcfbench.nn2d`` (ties to
        the lowest index; ``period`` > 0: dimension 0 periodic)."""
        q = np.ascontiguousarray(queries, dtype=np.float64)
        if q.shape[0] == 0:
            return np.zeros(0, dtype=np.int64)
        d2_of = _d2_periodic(period) if period > 0 else _d2_2d
        return self._nearest(q, np.ascontiguousarray(data, dtype=np.float64), period, True, d2_of)[1]

    def nearest_angles(self, pred_rel: np.ndarray, gt_rel: np.ndarray,
                       gt_angles: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray]:
        """``pcfbench.metrics.nn.nearest_angles``: the nearest predicted point per ground-truth ray
        in the 4D-Occ angle space and in (azimuth, elevation) with wrap-around."""
        g4, gw = gt_angles if gt_angles is not None else (angles_4docc(gt_rel), angles_az_el(gt_rel))
        return (self.nearest_2d(angles_4docc(pred_rel), g4),
                self.nearest_2d(angles_az_el(pred_rel), gw, period=TWO_PI))


def _coordinate_slack(queries: np.ndarray, points: np.ndarray) -> float:
    """Absolute bound on what rounding 3D coordinates to float32 moves a distance: none for
    coordinates that are float32 values already (the protocol's points are), else 2^-22 of the
    largest coordinate (both points' rounding, each axis)."""
    exact = all(np.array_equal(a.astype(np.float32).astype(np.float64), a) for a in (queries, points))
    if exact:
        return 1e-12
    return 2.0**-22 * max(float(np.abs(queries).max(initial=0.0)), float(np.abs(points).max(initial=0.0)))


def _d2_3d(q: np.ndarray, p: np.ndarray) -> np.ndarray:
    dx, dy, dz = q[..., 0] - p[..., 0], q[..., 1] - p[..., 1], q[..., 2] - p[..., 2]
    return (dx * dx + dz * dz) + dy * dy


def _d2_2d(q: np.ndarray, p: np.ndarray) -> np.ndarray:
    dx, dy = p[..., 0] - q[..., 0], p[..., 1] - q[..., 1]
    return dx * dx + dy * dy


def _d2_periodic(period: float):
    def d2(q: np.ndarray, p: np.ndarray) -> np.ndarray:
        dx = np.abs(p[..., 0] - q[..., 0])
        dx = np.minimum(dx, period - dx)
        dy = p[..., 1] - q[..., 1]
        return dx * dx + dy * dy
    return d2
