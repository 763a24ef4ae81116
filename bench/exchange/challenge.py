"""The Argoverse 2 4D occupancy forecasting challenge's JSON files (``cvpr23-evalkit``), both ways.

Layout, as the kit's README documents it::

    {"queries": [{"horizon": "3s",
                  "rays": {"<log_id>": {"<frame_id>": [ [[ox, oy, oz, dx, dy, dz], ...],   # future sweep 0
                                                        ... ]}}}]}                          # one list per sweep

A query file holds per ray its origin and unit direction; a submission replaces each ray's
six numbers by ``[d]``, the depth along it. ``<log_id>`` is the log (pcfbench's sequence
``split/<log_id>``), ``<frame_id>`` the t=0 sweep's file name, ``<timestamp_ns>.feather``.

pcfbench's files differ from the kit's own in what the rays are, not in layout (docs/
bring-your-own-method.md): every ground-truth ray of the sample (the kit keeps a 20 % subset),
in pcfbench's reference frame (for Argoverse 2 the ego frame at t=0; the kit's is the up
LiDAR's), on pcfbench's samples. A query file also carries ``"pcfbench"``: the answers of its
questions (:meth:`pcfbench.exchange.questions.Questions.answers`); a submission that keeps it is
checked against them, one without it by its horizon and its rays only.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from pcfbench.data import Forecast, Sample
from pcfbench.errors import PcfbenchError
from pcfbench.exchange.questions import Questions
from pcfbench.exchange.submission import SubmissionFile


def challenge_key(sequence: str, t0_timestamp_ns: int) -> tuple[str, str]:
    """(log id, frame id) of a sample: its sequence's last path part and its t=0 sweep's file name."""
    return sequence.rpartition("/")[2], f"{int(t0_timestamp_ns)}.feather"


def sample_challenge_key(sample: Sample) -> tuple[str, str]:
    return challenge_key(sample.sequence, int(sample.past_timestamps_ns[-1]))


def horizon(questions: Questions) -> str:
    return f"{questions.builder.setting.horizon_s:g}s"


def _write_json(path: Path, obj: Any) -> None:
    tmp = path.with_name(f".{path.name}.tmp")
    try:
        with open(tmp, "w") as fh:
            json.dump(obj, fh, separators=(",", ":"), allow_nan=False)
        tmp.replace(path)
    except OSError as exc:
        tmp.unlink(missing_ok=True)
        raise PcfbenchError(f"cannot write {path}: {exc.strerror or exc}") from None


def write_challenge_queries(questions: Questions, path: Path, progress=None) -> dict[str, int]:
    """The challenge query JSON of ``questions`` at ``path``: per sample and future sweep, each
    query ray's origin and unit direction (float64 numbers; the float32 directions exactly).
    Returns counts (samples, rays)."""
    rays: dict[str, dict[str, list]] = {}
    n_rays = 0
    for key in questions.keys:
        sample, _truth = questions.builder.build(*key)
        log, frame = sample_challenge_key(sample)
        sweeps = []
        for q in sample.queries:
            o = np.broadcast_to(np.asarray(q.origin_ref, np.float64), (len(q), 3))
            sweeps.append(np.hstack([o, q.directions_ref.astype(np.float64)]).tolist())
            n_rays += len(q)
        rays.setdefault(log, {})[frame] = sweeps
        if progress is not None:
            progress(1)
    _write_json(Path(path), {"queries": [{"horizon": horizon(questions), "rays": rays}], "pcfbench": questions.answers()})
    return {"samples": len(questions.keys), "rays": n_rays}


def _entries(path: Path, width: int) -> tuple[dict[str, Any], str, dict[tuple[str, str], list[np.ndarray]]]:
    """The parsed file, its horizon and per (log, frame) one (M_k, width) float64 array per
    future sweep; one error naming the file and the entry that is not so."""
    try:
        data = json.loads(Path(path).read_text())
    except (OSError, ValueError) as exc:
        raise PcfbenchError(f"cannot read {path} as JSON ({exc})") from None
    queries = data.get("queries") if isinstance(data, dict) else None
    if not isinstance(queries, list) or len(queries) != 1 or not isinstance(queries[0], dict) \
            or not isinstance(queries[0].get("rays"), dict) or not isinstance(queries[0].get("horizon"), str):
        raise PcfbenchError(f"{path} is not a challenge file: expected {{\"queries\": [{{\"horizon\": ..., \"rays\": "
                            "{log_id: {frame_id: [...]}}}]}, one entry")
    out = {}
    for log, frames in queries[0]["rays"].items():
        if not isinstance(frames, dict):
            raise PcfbenchError(f"{path}: log {log} holds {type(frames).__name__}, not an object of frames")
        for frame, sweeps in frames.items():
            where = f"{path}: log {log}, frame {frame}"
            if not isinstance(sweeps, list):
                raise PcfbenchError(f"{where}: expected a list of future sweeps, got {type(sweeps).__name__}")
            arrays = []
            for k, rows in enumerate(sweeps):
                try:
                    arr = np.asarray(rows, dtype=np.float64).reshape(-1, width) if rows == [] else np.asarray(rows, np.float64)
                except (ValueError, TypeError):
                    arr = None
                if arr is None or arr.ndim != 2 or arr.shape[1] != width:
                    got = "ragged or not numbers" if arr is None else f"shape {arr.shape}"
                    raise PcfbenchError(f"{where}, future sweep {k}: expected a list of [{'d' if width == 1 else '6 numbers'}] "
                                        f"per ray ({width} number(s) each), got {got}")
                arrays.append(arr)
            out[(log, frame)] = arrays
    return data, queries[0]["horizon"], out


def read_challenge_queries(path: Path) -> tuple[str, dict[tuple[str, str], list[tuple[np.ndarray, np.ndarray]]]]:
    """A challenge query file: its horizon and per (log, frame) the (origins (M, 3) float64,
    directions (M, 3) float32) of each future sweep."""
    _data, hz, entries = _entries(Path(path), 6)
    return hz, {k: [(a[:, :3], a[:, 3:].astype(np.float32)) for a in v] for k, v in entries.items()}


def open_challenge_submission(path: Path) -> SubmissionFile:
    """A challenge submission (a ``[d]`` per query ray) as a :class:`SubmissionFile` of depths."""
    data, hz, entries = _entries(Path(path), 1)

    def arrays(key: tuple[str, str]) -> dict[str, dict[int, np.ndarray]]:
        return {"depths": {k: a[:, 0] for k, a in enumerate(entries[key])}}

    return SubmissionFile(Path(path), "challenge-json", set(entries), data.get("pcfbench"), arrays,
                          key_of=sample_challenge_key, horizon=hz)


def ray_depths(sample: Sample, forecast: Forecast, execution=None) -> list[np.ndarray]:
    """One depth per query ray of each future sweep (float32): the forecast's depths, else the
    range of its point nearest to the ray in (azimuth, elevation) with wrap-around (the point
    pcfbench's ``l1_mean`` reads off a points forecast); 0 where a sweep's forecast is empty."""
    from pcfbench.metrics.nn import nearest_angles

    if forecast.depths is not None:
        return [np.asarray(d, np.float32) for d in forecast.depths]
    out = []
    for q, pts in zip(sample.queries, forecast.points_ref):
        if len(pts) == 0 or len(q) == 0:
            out.append(np.zeros(len(q), np.float32))
            continue
        rel = np.asarray(pts, np.float64) - np.asarray(q.origin_ref, np.float64)
        idx = nearest_angles(rel, q.directions_ref.astype(np.float64), execution)[1]
        out.append(np.sqrt(np.einsum("ij,ij->i", rel, rel))[idx].astype(np.float32))
    return out


def export_challenge(questions: Questions, method: Any, path: Path, progress=None) -> dict[str, int]:
    """Run ``method`` on every sample of ``questions`` and write its forecasts as a challenge
    submission (one ``[d]`` per query ray: :func:`ray_depths`), carrying the questions' answers."""
    from pcfbench.protocol.validate import validate_forecast

    rays: dict[str, dict[str, list]] = {}
    n_rays = 0
    for key in questions.keys:
        sample, _truth = questions.builder.build(*key)
        forecast = validate_forecast(sample, method.forecast(sample.for_method()))
        log, frame = sample_challenge_key(sample)
        depths = ray_depths(sample, forecast)
        rays.setdefault(log, {})[frame] = [d.astype(np.float64)[:, None].tolist() for d in depths]
        n_rays += sum(len(d) for d in depths)
        if progress is not None:
            progress(1)
    _write_json(Path(path), {"queries": [{"horizon": horizon(questions), "rays": rays}], "pcfbench": questions.answers()})
    return {"samples": len(questions.keys), "rays": n_rays}
