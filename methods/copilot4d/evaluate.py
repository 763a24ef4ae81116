"""Reconstruction evaluation in the shape of the paper's Table 7, and token caching."""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import torch

from pcfbench.execution import ExecutionContext
from pcfbench.boxes import Box
from pcfbench.methods.copilot4d.data import SweepSource, in_box
from pcfbench.methods.copilot4d.model import Tokenizer
from pcfbench.methods.copilot4d.options import check_readout
from pcfbench.methods.copilot4d.render import box_interval, logistic_noise_mask, render_depth, sample_along_rays
from pcfbench.training import autocast


@torch.no_grad()
def tokenize_sweep(model: Tokenizer, points: np.ndarray) -> torch.Tensor:
    """(T, T) token indices of one sensor-frame sweep."""
    cfg = model.cfg
    dev = next(model.parameters()).device
    p = torch.from_numpy(points[in_box(cfg, points)]).float().to(dev)
    with autocast(dev):
        z = model.encoder(p, torch.zeros(len(p), dtype=torch.long, device=dev), 1)
    return model.vq.codes_for(z.float())[0]


@torch.no_grad()
def decode(model: Tokenizer, codes: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The decoder's NFG (1, F, Z, X, Y) and coarse logits (float32) of one (T, T) token map, or
    of one (T, T, D) map of code embeddings (floating point: what the decoder reads after the
    codebook look-up); on the CPU the NFG's memory is channels last (what :func:`render_codes`
    marches)."""
    dev = next(model.parameters()).device
    channels_last = dev.type == "cpu"
    with autocast(dev):
        if codes.is_floating_point():
            size = (model.cfg.bev_tokens, model.cfg.bev_tokens, model.cfg.code_dim)
            if tuple(codes.shape) != size:
                raise ValueError(f"decode: a map of code embeddings is (tokens, tokens, code_dim) = {size}; got "
                                 f"{tuple(codes.shape)} (a token map holds integer codes)")
            nfg, coarse = model.decoder(codes[None].to(dev, model.vq.codebook.dtype), channels_last=channels_last)
        else:
            nfg, coarse = model.decode_codes(codes[None].to(dev), channels_last=channels_last)
    return nfg.float(), coarse


def rendering_kwargs(options) -> dict:
    """``render_codes`` keywords from a Copilot4D method's options (``options.RenderingOptions``):
    how the three forecasting methods and the oracle render token maps."""
    return {"threshold": options.threshold, "noise": options.noise, "readout": options.readout}


def median_depth(w: torch.Tensor, h: torch.Tensor, exit: torch.Tensor) -> torch.Tensor:
    """Per ray (rows of the sorted sample depths ``h`` with weights ``w``): the first h_j whose
    cumulative weight reaches half of the row's total; ``exit`` (R,) where the total is 0."""
    total = w.sum(dim=1)
    cdf = torch.cumsum(w, dim=1)
    j = torch.searchsorted(cdf, (0.5 * total)[:, None]).clamp(max=h.shape[1] - 1)
    return torch.where(total > 0, h.gather(1, j)[:, 0].to(exit.dtype), exit)


@torch.no_grad()
def render_codes(model: Tokenizer, codes: torch.Tensor, dirs: np.ndarray, *, skipping: bool = True,
                 samples: int | None = None, chunk: int = 4096, generator: torch.Generator | None = None,
                 far_bound: bool = True, threshold: float = 0.5, noise: bool = True,
                 origin: np.ndarray | None = None, decoded: tuple | None = None,
                 readout: str = "expected", torch_path: bool = False,
                 execution: ExecutionContext | None = None) -> np.ndarray:
    """Expected depth (equation 4) along unit rays for one (T, T) token map, from the sensor
    of the tokenized sweep or from ``origin`` (3,), a point in that sensor's frame (the rays'
    directions in the same frame).
    With ``skipping``, ray points are sampled only inside coarse voxels predicted non-empty
    (Logistic noise, threshold, max-pool; figure 8); otherwise uniformly over the grid box.
    With ``far_bound``, the transmittance left after the last sample puts its share of the
    depth at the grid's boundary (equation 4 plus a background term; training uses
    equation 4 alone, on returns inside the grid). ``decoded``: ``decode(model, codes)``
    already computed (rendering one token map from several origins decodes it once).

    ``readout`` turns the ray's weights w_i into one depth: ``expected`` is equation 4
    (sum w_i h_i, with ``far_bound``); ``median`` is the depth h_j at which the cumulative
    weight first reaches half of the ray's total weight, the median of where the ray ends
    given that it ends inside the grid (every query ray of the protocol is a return), and
    the grid's exit for a ray with no weight at all. Where the weight is split between a
    thin object and what lies behind it, the expected depth lands in the empty space between
    them; the median lands on one of the two.

    On the CPU the rays are marched by :func:`~.raymarch.march` (the same arithmetic fused per
    ray, several times faster, its rays shared out over ``execution``'s threads: a method passes
    its ``self.execution``; default the process's); ``torch_path`` (and any other device)
    renders with the differentiable torch functions that training uses, in chunks of ``chunk`` rays."""
    check_readout(readout)
    cfg = model.cfg
    dev = next(model.parameters()).device
    nfg, coarse = decoded if decoded is not None else decode(model, codes)
    mask = logistic_noise_mask(cfg, coarse.float(), noise=noise, generator=generator, threshold=threshold) if skipping else None
    n = samples or cfg.samples_per_ray
    if dev.type == "cpu" and not torch_path:  # one fused numba pass per ray (raymarch.py)
        from pcfbench.methods.copilot4d.raymarch import march

        dec = model.decoder
        mlp = tuple(t.detach().float().numpy() for t in (dec.mlp1.weight, dec.mlp1.bias, dec.mlp2.weight, dec.mlp2.bias))
        depth = march(cfg, nfg[0].permute(2, 3, 1, 0).contiguous().numpy(), None if mask is None else mask[0].numpy(),
                      np.zeros(3) if origin is None else np.asarray(origin), dirs, mlp, samples=n, readout=readout,
                      far_bound=far_bound, execution=execution)
        return depth.astype(np.float64)
    out = np.empty(len(dirs), dtype=np.float64)
    all_d = torch.from_numpy(np.ascontiguousarray(dirs, dtype=np.float32)).to(dev)
    o0 = torch.zeros(3, device=dev) if origin is None else torch.as_tensor(origin, dtype=torch.float32, device=dev)
    # rays in order of their exit from the grid box, so that each chunk's candidate points for
    # spatial skipping stop at that chunk's farthest exit (the same depths, fewer candidates)
    order = torch.argsort(box_interval(cfg, o0.expand_as(all_d), all_d)[1]).cpu()
    for s in range(0, len(dirs), chunk):
        idx = order[s: s + chunk]
        d = all_d[idx.to(dev)]
        o = o0.expand_as(d).contiguous()
        b = torch.zeros(len(d), dtype=torch.long, device=dev)
        h = sample_along_rays(cfg, o, d, b, mask, n, jitter=False)
        depth, w = render_depth(model.decoder, nfg, cfg, o, d, b, h)
        if readout == "median":
            depth = median_depth(w, h, box_interval(cfg, o, d)[1])
        elif far_bound:  # transmittance left at the end of the grid: the ray leaves it there
            depth = depth + (1.0 - w.sum(dim=1)).clamp(min=0.0) * box_interval(cfg, o, d)[1]
        out[idx.numpy()] = depth.double().cpu().numpy()
    return out


def render_queries(model: Tokenizer, codes, sample, T_frame_ref, *, generator: torch.Generator | None = None,
                   decoded: tuple | None = None, execution: ExecutionContext | None = None, **render) -> list[np.ndarray]:
    """Depths (m) along every future sweep's query rays of ``sample``, rendered from token maps.

    ``codes``: a list of one (T, T) token map (or (T, T, D) map of code embeddings, :func:`decode`)
    per future sweep, or one map for them all; map k was
    tokenized in a frame ``g_k``, and ``T_frame_ref`` gives ``T_g_ref`` (4, 4) per future sweep
    (or one for all): the query's origin and directions are moved from the reference frame into
    ``g_k`` and rendered there (:func:`render_codes` with ``render``: threshold, noise, readout).
    ``copilot4d-token-copy`` and ``copilot4d`` render the t=0 frame's maps (``T_g_ref`` = the
    inverse of the last past sensor pose) from each future sensor; a map tokenized in its own
    future sensor frame is rendered with ``T_g_ref`` = that sensor's inverse pose (origin 0)."""
    F = len(sample.queries)
    single = not isinstance(codes, (list, tuple))
    Ts = [np.asarray(T_frame_ref, np.float64)] * F if np.ndim(T_frame_ref) == 2 else list(T_frame_ref)
    if len(Ts) != F or (not single and len(codes) != F):
        raise ValueError(f"render_queries: {F} future sweeps, {len(Ts)} frames, "
                         f"{1 if single else len(codes)} token maps")
    if single and decoded is None:
        decoded = decode(model, codes)  # once: every future sweep renders the same tokens
    depths = []
    for k, q in enumerate(sample.queries):
        R, t = Ts[k][:3, :3], Ts[k][:3, 3]
        origin = R @ q.origin_ref + t
        dirs = (q.directions_ref.astype(np.float64) @ R.T).astype(np.float32)
        depths.append(render_codes(model, codes if single else codes[k], dirs, origin=origin, generator=generator,
                                   decoded=decoded if single else None, execution=execution, **render))
    return depths


#: Table 7's columns, each scored by the registered metric of that name (pcfbench.metrics).
TABLE7_METRICS = ("chamfer_nf", "l1_median", "l1_mean", "chamfer")


def sweep_errors(gt_points: np.ndarray, dirs: np.ndarray, pred_depth: np.ndarray, grid: Box | None = None) -> dict[str, float]:
    """Table-7 numbers of one sweep reconstructed along its own rays, scored by the registered
    metrics (``TABLE7_METRICS``) on a ``SweepContext`` whose reference frame is the sensor
    frame: NFCD within the ROI, L1 median and mean of depth along the ground-truth rays
    clamped to the ROI (the protocol's minimum range), and CD. With ``grid`` (the tokenizer's
    box), also the L1 median over the kept rays whose return lies inside it."""
    from pcfbench.data import RayQuery
    from pcfbench.metrics.base import SweepContext
    from pcfbench.plugins import get_plugins

    registry = get_plugins().metrics
    ctx = SweepContext(gt_points=np.asarray(gt_points, dtype=np.float32),
                       query=RayQuery(np.zeros(3), np.asarray(dirs, dtype=np.float32)),
                       pred_points=None, pred_depths=np.asarray(pred_depth, dtype=np.float64))
    out = {}
    if grid is not None:
        err, _ = ctx.ray_errors(np.asarray(pred_depth, dtype=np.float64))
        kept = ctx.ray_kept
        inside = grid.contains(np.asarray(gt_points))[kept]
        out["l1_median_in_grid"] = float(np.median(err[inside])) if inside.any() else float("nan")
        out["rays_in_grid"] = float(inside.sum() / max(kept.sum(), 1))
    return out | {name: float(registry.get(name)(ctx)) for name in TABLE7_METRICS}


SKIP_CANDIDATES = [(t, n) for t in (0.5, 0.2, 0.1, 0.05, 0.03, 0.02, 0.01) for n in (True, False)]


def calibrate_skipping(model: Tokenizer, source: SweepSource, *, sweeps: int = 4, rays: int = 4000, seed: int = 0) -> dict:
    """Pick the spatial-skipping threshold and noise (the paper gives no threshold) that give
    the lowest depth L1 median on a few sweeps of ``source`` (the training split)."""
    model.eval()
    rng = np.random.default_rng(seed)
    gen = torch.Generator().manual_seed(seed)
    picks = rng.choice(len(source), min(sweeps, len(source)), replace=False)
    scores = {c: [] for c in SKIP_CANDIDATES}
    for k in picks:
        pts = source.points(int(k))
        pts = pts[np.linalg.norm(pts, axis=1) > 0.5]
        pts = pts[rng.choice(len(pts), min(rays, len(pts)), replace=False)]
        r = np.linalg.norm(pts, axis=1)
        dirs = (pts / r[:, None]).astype(np.float32)
        codes = tokenize_sweep(model, source.points(int(k)))
        for (t, n) in SKIP_CANDIDATES:
            d = render_codes(model, codes, dirs, skipping=True, threshold=t, noise=n, generator=gen)
            scores[(t, n)].append(float(np.median(np.abs(d - r))))
    best = min(SKIP_CANDIDATES, key=lambda c: np.mean(scores[c]))
    return {"threshold": best[0], "noise": best[1], "calibration_l1_median": float(np.mean(scores[best])),
            "paper_setting_l1_median": float(np.mean(scores[(0.5, True)])), "split": source.split, "sweeps": len(picks)}


def evaluate_reconstruction(model: Tokenizer, source: SweepSource, *, max_sweeps: int = 40, seed: int = 0,
                            skip: dict | None = None, render: dict | None = None, log=print) -> dict:
    """Reconstruct up to ``max_sweeps`` evenly spaced sweeps of ``source`` through their tokens,
    with spatial skipping as in the paper (Logistic noise, threshold 0.5, expected depth), with
    the calibrated skipping setting ``skip`` (if given), with the forecasting methods' rendering
    ``render`` (``rendering_kwargs``, if given) and without skipping; per-sweep metrics averaged
    flat (docs/protocol.md section 4)."""
    model.eval()
    picks = np.unique(np.linspace(0, len(source) - 1, min(max_sweeps, len(source))).round().astype(int))
    gen = torch.Generator().manual_seed(seed)
    rows = {"skipping": [], **({"calibrated": []} if skip else {}), **({"method": []} if render else {}), "uniform": []}
    cfg = model.cfg
    grid = Box((cfg.x_range[0], cfg.y_range[0], cfg.z_range[0]), (cfg.x_range[1], cfg.y_range[1], cfg.z_range[1]))
    used = np.zeros(model.cfg.codebook_size, dtype=np.int64)
    t0 = time.monotonic()
    for k in picks:
        pts = source.points(int(k))
        r = np.linalg.norm(pts, axis=1)
        pts = pts[r > 0.5]
        dirs = (pts / np.linalg.norm(pts, axis=1, keepdims=True)).astype(np.float64)
        codes = tokenize_sweep(model, pts)
        used += np.bincount(codes.flatten().cpu().numpy(), minlength=used.size)
        for mode in rows:
            kw = ({"threshold": skip["threshold"], "noise": skip["noise"]} if mode == "calibrated"
                  else render if mode == "method" else {})
            depth = render_codes(model, codes, dirs.astype(np.float32), skipping=mode != "uniform", generator=gen, **kw)
            rows[mode].append(sweep_errors(pts.astype(np.float64), dirs, depth, grid))
    p = used / max(used.sum(), 1)
    nz = p[p > 0]
    result = {
        "sweeps": int(len(picks)),
        "split": source.split,
        "dataset": source.adapter.name,
        "codebook_usage": float((used > 0).mean()),
        "codebook_perplexity": float(np.exp(-(nz * np.log(nz)).sum())),
        "eval_s": time.monotonic() - t0,
        "skip_calibration": skip,
        "render": render,
    }
    for mode, rs in rows.items():
        result[mode] = {k: float(np.nanmean([r[k] for r in rs])) for k in rs[0]}
    return result


#: the rows of the reconstruction report, in order
MODES = ("skipping", "calibrated", "method", "uniform")


def write_report(result: dict, meta: dict, out_dir: Path, stem: str) -> tuple[Path, Path]:
    """Markdown table in the shape of Table 7 plus a JSON of everything."""
    out_dir.mkdir(parents=True, exist_ok=True)
    js = out_dir / f"{stem}.json"
    js.write_text(json.dumps({"result": result, "meta": meta}, indent=2, default=str))
    lines = [
        f"# Copilot4D tokenizer reconstruction ({meta.get('config')} config, {result['dataset']} {result['split']})",
        "",
        f"{result['sweeps']} sweeps reconstructed from their tokens; metrics within the ROI as in docs/protocol.md section 4 "
        "(sensor frame = reference frame), flat mean over sweeps.",
        "",
        "| Rendering | Chamfer (within ROI) m^2 | L1 Median m | L1 Mean m | Chamfer m^2 | L1 Median, returns inside the grid m |",
        "|---|---|---|---|---|---|",
    ]
    names = {"skipping": "Spatial skipping as in the paper (Logistic noise, threshold 0.5)",
             "uniform": "Uniform ray samples (no skipping)"}
    if result.get("skip_calibration"):
        c = result["skip_calibration"]
        names["calibrated"] = (f"Spatial skipping, threshold {c['threshold']} {'with' if c['noise'] else 'without'} "
                               f"noise (calibrated on {c['sweeps']} {c['split']} sweeps)")
    if result.get("render"):
        r = result["render"]
        names["method"] = (f"The forecasting methods' rendering: spatial skipping, threshold {r['threshold']} "
                           f"{'with' if r['noise'] else 'without'} noise, {r['readout']} depth")
    for mode in [m for m in MODES if m in result]:
        r = result[mode]
        lines.append(f"| {names[mode]} | {r['chamfer_nf']:.3f} | {r['l1_median']:.3f} | {r['l1_mean']:.3f} | {r['chamfer']:.3f} "
                     f"| {r.get('l1_median_in_grid', float('nan')):.3f} |")
    lines += [
        "",
        f"- codebook usage on these sweeps: {result['codebook_usage']:.1%} of {meta.get('codebook_size')} codes "
        f"(perplexity {result['codebook_perplexity']:.1f})",
        f"- returns inside the tokenizer grid: {result['uniform'].get('rays_in_grid', float('nan')):.1%} of the ROI-kept rays "
        "(the others end at the grid boundary and count as errors in the first four columns)",
    ]
    for k, v in meta.items():
        lines.append(f"- {k}: {v}")
    md = out_dir / f"{stem}.md"
    md.write_text("\n".join(lines) + "\n")
    import csv

    with open(out_dir / f"{stem}.csv", "w", newline="") as f:
        w = csv.writer(f)
        cols = [*TABLE7_METRICS, "l1_median_in_grid", "rays_in_grid"]
        w.writerow(["rendering", "dataset", "split", "sweeps", *cols])
        for mode in [m for m in MODES if m in result]:
            w.writerow([names[mode], result["dataset"], result["split"], result["sweeps"],
                        *(f"{result[mode].get(k, float('nan')):.6g}" for k in cols)])
    return md, js


@torch.no_grad()
def tokenize_split(model: Tokenizer, adapter, split: str, out_dir: Path, log=print) -> list[Path]:
    """Cache the token maps of every sweep of ``split``: one .npz per sequence with ``tokens``
    (T, H, W) int16, ``T_world_sensor`` and ``timestamps_ns``."""
    model.eval()
    out_dir.mkdir(parents=True, exist_ok=True)
    written = []
    for name in adapter.sequence_names(split):
        seq = adapter.sequence(name)
        maps = [tokenize_sweep(model, adapter.ego_box.remove(seq.load_points(i))).cpu().numpy().astype(np.int16)
                for i in range(len(seq))]
        path = out_dir / f"{name}.npz"
        np.savez_compressed(path, tokens=np.stack(maps), T_world_sensor=seq.T_world_sensor,
                            timestamps_ns=seq.timestamps_ns, codebook_size=model.cfg.codebook_size)
        written.append(path)
        log(f"{name}: {len(maps)} token maps -> {path}")
    return written


def changed_share(codes: torch.Tensor, last: torch.Tensor) -> float:
    """The share of tokens of ``codes`` that differ from ``last`` (two maps of one shape)."""
    if codes.shape != last.shape:
        raise ValueError(f"token maps of shapes {tuple(codes.shape)} and {tuple(last.shape)}")
    return float((codes != last).float().mean())


#: the edges (m) of the rings of distance from the t=0 sensor the token counts are also split by
RING_EDGES = (20.0, 40.0, 60.0)


def token_rings(cfg, shape: tuple[int, int], edges=RING_EDGES) -> np.ndarray:
    """Per token of a (H, W) map over the tokenizer's grid (``cfg.x_range``, ``cfg.y_range``; the
    t=0 sensor at the origin), the index of the ring its centre's distance from the origin falls
    in: 0 below ``edges[0]``, ..., ``len(edges)`` at or beyond the last edge."""
    H, W = shape
    x = cfg.x_range[0] + (np.arange(H) + 0.5) * (cfg.x_range[1] - cfg.x_range[0]) / H
    y = cfg.y_range[0] + (np.arange(W) + 0.5) * (cfg.y_range[1] - cfg.y_range[0]) / W
    return np.searchsorted(np.asarray(edges, np.float64), np.hypot(x[:, None], y[None, :]), side="right")


def ring_labels(edges=RING_EDGES) -> list[str]:
    bounds = [0.0, *edges]
    return [f"{a:g}-{b:g} m" for a, b in zip(bounds, bounds[1:])] + [f"{edges[-1]:g} m and beyond"]


def changed_by_ring(cfg, codes: torch.Tensor, last: torch.Tensor) -> tuple[np.ndarray, np.ndarray]:
    """Per ring of :func:`token_rings` (distance from the sensor at the grid's centre), the number
    of tokens of ``codes`` that differ from ``last`` and the number of tokens (two maps of one shape)."""
    if codes.shape != last.shape:
        raise ValueError(f"token maps of shapes {tuple(codes.shape)} and {tuple(last.shape)}")
    rings = token_rings(cfg, tuple(last.shape))
    n = len(RING_EDGES) + 1
    diff = (codes != last).cpu().numpy()
    return np.bincount(rings[diff], minlength=n), np.bincount(rings.ravel(), minlength=n)


#: the frames a world model's target can be tokenized in (issue 42): ``t0``, every sweep of a
#: window moved into the t=0 sensor frame (what ``build_windows`` feeds the world model);
#: ``own``, each sweep in its own sensor frame, rendered from its own origin.
CEILING_FRAMES = ("t0", "own")
