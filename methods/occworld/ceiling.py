"""OccWorld's ceiling (issue 43's first bar): a perfect prediction of the world model's target
for the ground-truth future, rendered exactly as ``occworld`` renders, scored by the harness
beside ``occworld-occ-copy`` (the same tokenizer: the last past occupancy's tokens decoded and
rendered at the future poses) and copy-last on the same samples (Copilot4D's
``ceiling.score_beside``). If the ceiling does not beat the occupancy copy, no training will.
``pcfbench occworld-ceiling``.

The target of future sweep k (its points, ego returns removed), as ``occworld`` trains on it:
``frame="own"``: labelled (free / occupied / unknown) from its rays in its own sensor frame,
tokenized, decoded and rendered from its own origin; ``frame="t0"``: moved into the t=0 sensor
frame, labelled there from its sensor's position in that frame, tokenized, decoded and
rendered from that position. Also per future sweep, the share of target tokens that differ
from the t=0 sweep's (the occupancy copy's tokens in the t=0 frame; in its own frame for ``own``)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pcfbench.errors import PcfbenchError
from pcfbench.methods.occworld import occ_copy as oc


class LabelTokens:
    """The bound of the representation itself (``perfect``): a tokenizer whose tokens are the
    occupancy labels and whose decoding is certain (occupied: 1, free and unknown: 0), on the
    grid of ``cfg``. What no trained tokenizer can beat: the voxels and the rendering alone."""

    def __init__(self, cfg) -> None:
        self.cfg = cfg

    def eval(self):
        return self

    @staticmethod
    def tokenize(model, labels: np.ndarray) -> np.ndarray:
        return labels

    @staticmethod
    def decode(model, codes) -> np.ndarray:
        from pcfbench.methods.occworld.occupancy import OCCUPIED

        return (np.asarray(codes) == OCCUPIED) * 1.0, None


def surface_grid(cfg, points_sensor: np.ndarray, T_frame_sensor: np.ndarray | None = None, at: str = "front"):
    """A sweep's perfect grid with sub-voxel planes (``occ_copy.surface_targets``, offsets ``at``):
    (labels, occupancy (occupied 1, else 0), normals from its free voxels, offsets of its
    returns), in the frame ``T_frame_sensor`` maps its sensor frame into (None: its own)."""
    from pcfbench.methods.occworld.occupancy import OCCUPIED

    labels, normals, offsets = oc.surface_targets(cfg, points_sensor, T_frame_sensor, at)
    return labels, (labels == OCCUPIED) * 1.0, normals, offsets


def render_surface_sample(cfg, grids, sample, T_frame_ref) -> list[np.ndarray]:
    """As ``occ_copy.render_sample``, through ``surface_grid``s (one per future sweep, or one for all)."""
    from pcfbench.methods.occworld.surface import render_surface

    F = sample.num_future
    Ts = [np.asarray(T_frame_ref, np.float64)] * F if np.ndim(T_frame_ref) == 2 else list(T_frame_ref)
    gs = [grids] * F if isinstance(grids, tuple) else list(grids)
    grid = oc.grid_of(cfg)
    out = []
    for k, q in enumerate(sample.queries):
        R, t = Ts[k][:3, :3], Ts[k][:3, 3]
        _, prob, normals, offsets = gs[k]
        out.append(render_surface(grid, prob, normals, offsets, R @ q.origin_ref + t, q.directions_ref.astype(np.float64) @ R.T))
    return out


def evaluate_ceiling(model, adapter, split: str, setting: str, *, frame: str = "own", readout: str = "expected",
                     surface: str = "none", max_samples: int | None = None, log=print) -> dict:
    """The ceiling of ``occworld`` on the tokenizer ``model`` (a ``SceneTokenizer``, or a
    ``LabelTokens`` for the representation's own bound), beside ``occworld-occ-copy`` and
    copy-last. ``surface="front"`` or ``"mean"`` (``LabelTokens`` only) renders both through the labels' sub-voxel planes (``surface.py``) instead of
    ``readout`` (a trained tokenizer with the offset head renders its own planes with
    ``readout="surface"``). Returns per-entry means (``means``), ``rows``, ``changed`` (mean share and per
    step), ``samples`` and ``sweeps``."""
    from pcfbench.methods.occworld.surface import SURFACES

    if surface not in SURFACES:
        raise PcfbenchError(f"ceiling surface {surface!r}: expected one of {', '.join(SURFACES)}")
    if surface != "none" and not isinstance(model, LabelTokens):
        raise PcfbenchError(f"ceiling surface={surface}: only with perfect tokens (--perfect); a trained tokenizer "
                            "renders the planes it decodes (readout=surface)")
    from pcfbench.data import Forecast
    from pcfbench.methods.copilot4d.ceiling import score_beside
    from pcfbench.methods.copy_last import CopyLast

    if frame not in oc.FRAMES:
        raise PcfbenchError(f"ceiling frame {frame!r}: expected one of {', '.join(oc.FRAMES)}")
    model.eval()
    cfg = model.cfg
    tokenize, decode = ((LabelTokens.tokenize, LabelTokens.decode) if isinstance(model, LabelTokens)
                        else (oc.tokenize_labels, oc.decode_grid))
    copy_last = CopyLast()
    changed: list[list[float]] = []

    def ceiling(sample, builder, seq_name: str, ref: int):
        seq = builder.sequence(seq_name)
        stride = builder.setting.stride
        T_s0_ref = np.linalg.inv(sample.past_T_ref_sensor[-1])
        last = tokenize(model, oc.sweep_labels(cfg, builder.points_sensor(seq, ref)))
        probs, frames, shares = [], [], []
        for k in range(sample.num_future):
            pts = builder.points_sensor(seq, ref + (k + 1) * stride)
            if surface != "none":
                T = T_s0_ref @ sample.future_T_ref_sensor[k] if frame == "t0" else None
                probs.append(surface_grid(cfg, pts, T, surface))
                frames.append(T_s0_ref if frame == "t0" else np.linalg.inv(sample.future_T_ref_sensor[k]))
                shares.append(float((probs[-1][0] != np.asarray(last)).mean()))
                continue
            if frame == "t0":
                codes = tokenize(model, oc.sweep_labels(cfg, pts, T_s0_ref @ sample.future_T_ref_sensor[k]))
                frames.append(T_s0_ref)
            else:
                codes = tokenize(model, oc.sweep_labels(cfg, pts))
                frames.append(np.linalg.inv(sample.future_T_ref_sensor[k]))
            shares.append(float((np.asarray(codes) != np.asarray(last)).mean()))
            probs.append(decode(model, codes))
        changed.append(shares)
        if surface != "none":
            return Forecast.from_depths(sample, render_surface_sample(cfg, probs, sample, frames))
        return Forecast.from_depths(sample, oc.render_sample(model, probs, sample, frames, readout))

    def occ_copy(sample, *_):
        sample = sample.for_method()
        if surface == "none":
            return oc.copy_forecast(model, sample, readout, tokenize, decode)
        T_s0_ref = np.linalg.inv(sample.past_T_ref_sensor[-1])
        last = sample.past_points_ref[-1].astype(np.float64) @ T_s0_ref[:3, :3].T + T_s0_ref[:3, 3]
        return Forecast.from_depths(sample, render_surface_sample(cfg, surface_grid(cfg, last, None, surface), sample, T_s0_ref))

    res = score_beside(adapter, split, setting, {
        "ceiling": ceiling,
        "occworld-occ-copy": occ_copy,
        "copy-last": lambda sample, *_: copy_last.forecast(sample.for_method())},
        max_samples=max_samples, log=log, label=f"occworld ceiling ({frame})")
    ch = np.asarray(changed, np.float64)
    return {"setting": setting, "split": split, "dataset": adapter.name, "frame": frame,
            "readout": readout if surface == "none" else f"surface={surface}",
            "samples": res["samples"], "of_samples": res["of_samples"],
            "sweeps": len(res["rows"]["ceiling"]), "eval_s": res["eval_s"],
            "means": res["means"], "rows": res["rows"],
            "changed": {"mean": float(ch.mean()), "per_step": [float(v) for v in ch.mean(axis=0)]}}


def write_ceiling(result: dict, meta: dict, out_dir: Path, stem: str) -> tuple[Path, Path]:
    """The ceiling as Markdown and CSV: its means, the occupancy copy's and copy-last's from the
    same loop, and the ratios, labelled as a bound that sees the future."""
    how = {"own": "labelled from its rays in its own sensor frame, tokenized, decoded and rendered from its own origin",
           "t0": "moved into the t=0 sensor frame, labelled there, tokenized, decoded and rendered from its sensor's "
                 "position in that frame"}[result["frame"]]
    ch = result["changed"]
    head = [
        f"# OccWorld: the world model's ceiling ({meta.get('config')} tokenizer, {result['dataset']} "
        f"{result['split']}, {result['setting']}, frame {result['frame']})",
        "",
        "**A bound, not a method: it sees the future.** Each ground-truth future sweep is " + how + f" ({result['readout']} "
        "depth), as `occworld` renders its forecast. `occworld-occ-copy` (the same tokenizer) and copy-last are "
        "scored in the same loop on the same samples by the same registered metrics; means are flat over (sample, "
        "future sweep).",
        "",
        f"{result['samples']} samples, {result['sweeps']} future sweeps; evaluation took {result['eval_s']:.0f} s. "
        f"Target tokens that differ from the t=0 sweep's: {ch['mean']:.1%} on average "
        f"({', '.join(f'{v:.0%}' for v in ch['per_step'])} by future step).",
        "",
    ]
    from pcfbench.methods.copilot4d.ceiling import write_beside

    return write_beside(result, meta, out_dir, stem, copy="occworld-occ-copy",
                        target="occworld's target", head=head, issue=43, columns=("readout",))
