"""Copilot4D on a GPU: the paper configuration's speed and memory, and a world model trained on
the GPU for a few minutes, judged in token space against the token copy (docs/copilot4d.md).

Run from the repository root with the package importable (installed, or the tree that
``docs/experiments/copilot4d_gpu.sh`` builds), the staged inputs in ``--inputs``:

- ``train-s2.npz``, ``train-s6.npz``, ``test-s2.npz``, ``test-s6.npz``: token windows (A, 10,
  H, W) and their poses (A, 10, 4, 4) of synthetic-town's train and test splits, tokenized by
  the tiny tokenizer (``forecaster.build_windows``; test windows anchored at every sweep);
- ``tiny-copilot4d.pt`` (optional): the weights of the CPU-trained tiny copilot4d checkpoint;
- ``kitti8.npz`` (optional): a few real KITTI sweeps, ``points`` (n, 3) and ``offsets``, for
  the paper tokenizer's training step;
- ``samples-kitti-1s.npz`` (optional): the world model's inputs for synthetic-town's kitti-1s
  test samples; their forecast tokens come back in ``replay-tokens.npz``.

Every part writes its figures into ``--out``/results.json as soon as it has them, so a run cut
short keeps what it measured. ``--smoke`` runs every part at toy sizes on the CPU (a check of
this script, not a measurement).
"""

from __future__ import annotations

import argparse
import json
import time
import traceback
from pathlib import Path

import numpy as np
import torch

from pcfbench.methods.copilot4d import diffusion as D
from pcfbench.methods.copilot4d.config import PAPER as PAPER_TOKENIZER
from pcfbench.methods.copilot4d.config import TINY as TINY_TOKENIZER
from pcfbench.methods.copilot4d.forecaster import train_world, world_config_for
from pcfbench.methods.copilot4d.train import autocast, default_device
from pcfbench.methods.copilot4d.world import WorldModel, causal_mask, count_parameters
from pcfbench.methods.copilot4d.world_config import PAPER, TINY

RESULTS: dict = {}


def record(out: Path, key: str, value) -> None:
    RESULTS[key] = value
    (out / "results.json").write_text(json.dumps(RESULTS, indent=1, default=float))
    print(f"[{key}] {json.dumps(value, default=float)[:600]}", flush=True)
    return value


def sync(dev: torch.device) -> None:
    if dev.type == "cuda":
        torch.cuda.synchronize()


def peak_gib(dev: torch.device) -> float | None:
    return torch.cuda.max_memory_allocated() / 2**30 if dev.type == "cuda" else None


def reset_peak(dev: torch.device) -> None:
    if dev.type == "cuda":
        torch.cuda.empty_cache()
        torch.cuda.reset_peak_memory_stats()


class Run:
    """What train_world / train need of a TrainingRun: a wall-clock budget, no checkpoints."""

    def __init__(self, budget_s: float) -> None:
        self.deadline = time.monotonic() + budget_s
        self.saves = 0

    def resume(self):
        return None

    def start(self, total, done):
        pass

    def should_stop(self) -> bool:
        return time.monotonic() > self.deadline

    def update(self, n, **kw):
        pass

    def save(self, step, weights, state, *, config, complete):
        self.saves += 1


# ----------------------------------------------------------------------------- paper world model
def time_train_steps(model, cfg, dev, batch: int, steps: int, warm: int) -> dict:
    """Median seconds per Algorithm-1 training step (AdamW, bf16 autocast on CUDA) on random
    codes, and the peak memory."""
    opt = D.make_optimizer(model, cfg)
    model.train()
    gen = torch.Generator(dev).manual_seed(0)
    T, G = cfg.n_frames, cfg.token_grid
    x0 = torch.randint(0, cfg.codebook_size, (batch, T, G, G), device=dev, generator=gen)
    poses = torch.eye(4, device=dev).expand(batch, T, 4, 4).contiguous()
    poses[..., 0, 3] = torch.arange(T, device=dev, dtype=torch.float32) - cfg.n_past + 1
    reset_peak(dev)
    times = []
    for i in range(warm + steps):
        sync(dev)
        t0 = time.perf_counter()
        with autocast(dev):
            loss, _ = D.training_loss(model, x0, poses, cfg.n_past, D.COPILOT4D, cfg.label_smoothing, generator=gen)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), cfg.grad_clip)
        opt.step()
        sync(dev)
        if i >= warm:
            times.append(time.perf_counter() - t0)
    med = float(np.median(times))
    return {"batch": batch, "steps_timed": steps, "median_step_s": med, "iterations_per_s": 1.0 / med,
            "min_step_s": float(np.min(times)), "peak_memory_gib": peak_gib(dev)}


def time_sampling(model, cfg, dev, guidance: float, n_future: int, reps: int, use_autocast: bool) -> dict:
    """Seconds per future frame of Algorithm 2 (10 steps, batch 1) forecasting ``n_future``
    frames after cfg.n_past random past frames, the past cached."""
    model.eval()
    gen = torch.Generator(dev).manual_seed(1)
    G = cfg.token_grid
    past = torch.randint(0, cfg.codebook_size, (1, cfg.n_past, G, G), device=dev, generator=gen)
    T = cfg.n_past + n_future
    poses = torch.eye(4, device=dev).expand(1, T, 4, 4).contiguous()
    poses[..., 0, 3] = torch.arange(T, device=dev, dtype=torch.float32) - cfg.n_past + 1
    ctx = autocast(dev) if use_autocast else torch.autocast(dev.type, enabled=False)
    reset_peak(dev)
    times = []
    for i in range(reps + 1):
        sync(dev)
        t0 = time.perf_counter()
        with ctx:
            D.forecast_tokens(model, past, poses, n_future, steps=10, guidance=guidance, generator=gen)
        sync(dev)
        if i:
            times.append((time.perf_counter() - t0) / n_future)
    med = float(np.median(times))
    return {"guidance": guidance, "bf16_autocast": use_autocast and dev.type == "cuda", "n_future": n_future,
            "median_s_per_future_frame": med, "frames_per_s": 1.0 / med, "peak_memory_gib": peak_gib(dev)}


# ----------------------------------------------------------------------------- token-space judge
@torch.no_grad()
def judge(model, cfg, windows: dict, dev, *, guidance: float, top_k: int, revise: bool, seed: int,
          batch: int = 16) -> dict:
    """Forecast every window's future from its clean past with Algorithm 2 and compare with the
    true future codes: accuracy per future frame, overall, and on the tokens that differ from the
    t=0 map (what a copy gets wrong); also the first future frame's arg max, all of it masked."""
    model.eval()
    toks = torch.from_numpy(windows["tokens"].astype(np.int64))
    poses = torch.from_numpy(windows["poses"].astype(np.float32))
    P, F = cfg.n_past, cfg.n_future
    gen = torch.Generator(dev).manual_seed(seed)
    hit = torch.zeros(F)
    hit_changed = torch.zeros(F)
    n_changed = torch.zeros(F)
    argmax_hit, n_tok = 0.0, 0
    for s in range(0, len(toks), batch):
        x = toks[s:s + batch].to(dev)
        p = poses[s:s + batch].to(dev)
        with autocast(dev):
            fut = D.forecast_tokens(model, x[:, :P], p, F, steps=10, guidance=guidance, top_k=top_k,
                                    revise=revise, generator=gen)
            masked = torch.cat([x[:, :P], torch.full_like(x[:, P:P + 1], model.mask_token)], 1)
            logits = model(masked, p[:, :P + 1], causal_mask(P + 1, dev))[:, -1]
        truth = x[:, P:]
        changed = truth != x[:, P - 1:P]
        ok = fut == truth
        hit += ok.float().mean((2, 3)).sum(0).cpu()
        hit_changed += (ok & changed).float().sum((0, 2, 3)).cpu()
        n_changed += changed.float().sum((0, 2, 3)).cpu()
        argmax_hit += float((logits.argmax(-1) == truth[:, 0]).float().sum())
        n_tok += truth[:, 0].numel()
    n = len(toks)
    return {"windows": n, "accuracy_per_future_frame": (hit / n).tolist(), "accuracy": float(hit.sum() / (n * F)),
            "accuracy_on_changed": float(hit_changed.sum() / n_changed.sum()),
            "first_frame_argmax_accuracy": argmax_hit / n_tok}


def copy_accuracy(windows: dict, n_past: int) -> dict:
    t = windows["tokens"]
    ok = t[:, n_past:] == t[:, n_past - 1:n_past]
    return {"windows": len(t), "accuracy_per_future_frame": ok.mean((0, 2, 3)).tolist(), "accuracy": float(ok.mean()),
            "accuracy_on_changed": 0.0}


@torch.no_grad()
def replay(runs, samples: Path, out: Path, dev, smoke: bool = False) -> dict:
    """Algorithm 2 on the staged samples' world-model inputs (as ``Copilot4D.forecast_tokens``
    computes them, one generator for the batch instead of one seed per sample), for each model
    with the defaults (w = 2, top-3) and, for the wide one, w = 0 with the arg max; writes
    ``replay-tokens.npz``: sample_ids and, per run, (S, F, H, W) int16 codes."""
    z = np.load(samples)
    past = torch.from_numpy(z["tokens"].astype(np.int64))
    poses = torch.from_numpy(z["poses"].astype(np.float32))
    if smoke:
        past, poses = past[:2], poses[:2]
    arrays = {"sample_ids": z["sample_ids"][:len(past)], "tokenizer_sha256": z["tokenizer_sha256"]}
    t0 = time.perf_counter()
    for name, model, cfg in runs:
        model.eval()
        for w, k in ((2.0, 3), (0.0, 1)) if name == "gpu" else ((2.0, 3),):
            gen = torch.Generator(dev).manual_seed(7)
            parts = []
            for s in range(0, len(past), 28):
                with autocast(dev):
                    parts.append(D.forecast_tokens(model, past[s:s + 28].to(dev), poses[s:s + 28].to(dev),
                                                   poses.shape[1] - past.shape[1], steps=10, guidance=w, top_k=k,
                                                   generator=gen).cpu())
            arrays[f"{name}_w{w:g}_top{k}"] = torch.cat(parts).numpy().astype(np.int16)
    np.savez_compressed(out / "replay-tokens.npz", **arrays)
    return {"samples": len(past), "runs": [k for k in arrays if k not in ("sample_ids", "tokenizer_sha256")],
            "seconds": time.perf_counter() - t0}


def load_windows(inputs: Path, split: str) -> dict:
    parts = [np.load(inputs / f"{split}-s{s}.npz") for s in (2, 6)]
    return {"tokens": np.concatenate([p["tokens"] for p in parts]), "poses": np.concatenate([p["poses"] for p in parts]),
            "n": [len(p["tokens"]) for p in parts]}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--inputs", type=Path, default=Path(".gpu"))
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--train-budget", type=float, default=240.0, help="seconds of world-model training")
    ap.add_argument("--total-budget", type=float, default=480.0, help="skip parts that would end after this")
    ap.add_argument("--smoke", action="store_true", help="toy sizes on the CPU: checks the script only")
    ap.add_argument("--parts", default="train_step,sampling,tokenizer,wide",
                    help="comma-separated: train_step, sampling (the paper world model), tokenizer (the paper "
                         "tokenizer's step), wide (train the wide model and judge it)")
    ap.add_argument("--batches", default="8,4,2,1", help="paper world-model batches to try, the first that fits")
    ap.add_argument("--wide-steps", type=int, default=0,
                    help="the wide model's training steps (0: as many as --train-budget allows, by a timed probe)")
    a = ap.parse_args()
    parts = set(a.parts.split(","))
    a.out.mkdir(parents=True, exist_ok=True)
    t_start = time.monotonic()
    dev = torch.device("cpu") if a.smoke else default_device()
    env = {"torch": torch.__version__, "device": str(dev), "smoke": a.smoke}
    if dev.type == "cuda":
        env["gpu"] = torch.cuda.get_device_name()
        torch.backends.cuda.matmul.allow_tf32 = True
        torch.backends.cudnn.allow_tf32 = True
    record(a.out, "env", env)

    def left() -> float:
        return a.total_budget - (time.monotonic() - t_start)

    def part(name, fn, need_s: float):
        if left() < need_s:
            record(a.out, name, {"skipped": f"{left():.0f} s left, needs about {need_s:.0f}"})
            return None
        try:
            return fn()
        except Exception as exc:  # one part failing (say out of memory) must not lose the others
            traceback.print_exc()
            record(a.out, name, {"error": f"{type(exc).__name__}: {str(exc)[:300]}"})
            if dev.type == "cuda":
                torch.cuda.empty_cache()
            return None

    # 1. the paper world model: size, training step, sampling speed
    paper = PAPER if not a.smoke else TINY.with_overrides(token_grid=32, codebook_size=64)
    torch.manual_seed(0)
    model = WorldModel(paper).to(dev)
    record(a.out, "paper_world_model", {"parameters": count_parameters(model), "token_grid": paper.token_grid,
                                         "codebook_size": paper.codebook_size, "frames": paper.n_frames})
    for bs in ([int(b) for b in a.batches.split(",")] if "train_step" in parts and not a.smoke else
               [1] if "train_step" in parts else []):  # A.3's batch of 8 first; smaller if it does not fit
        if part(f"paper_train_step_b{bs}", lambda bs=bs: record(
                a.out, f"paper_train_step_b{bs}", time_train_steps(model, paper, dev, bs, 10 if not a.smoke else 2,
                                                                   3 if not a.smoke else 1)), 60) is not None:
            break
    for w, ac in ((2.0, True), (0.0, True), (2.0, False)) if "sampling" in parts else ():
        key = f"paper_sampling_w{w:g}_{'bf16' if ac else 'fp32'}"
        part(key, lambda w=w, ac=ac, key=key: record(
            a.out, key, time_sampling(model, paper, dev, w, paper.n_future, 3 if not a.smoke else 1, ac)), 40)
    del model
    if dev.type == "cuda":
        torch.cuda.empty_cache()

    # 2. the paper tokenizer's training step on real KITTI sweeps
    kitti = a.inputs / "kitti8.npz"
    if kitti.is_file() and "tokenizer" in parts:
        def tok_step():
            from pcfbench.methods.copilot4d.train import train

            z = np.load(kitti)
            clouds = np.split(z["points"], z["offsets"][1:-1])

            class Source:
                def __len__(self):
                    return len(clouds)

                def points(self, k):
                    return clouds[k]

            cfg = PAPER_TOKENIZER if not a.smoke else TINY_TOKENIZER
            steps = 8 if not a.smoke else 2
            cfg = cfg.with_overrides(log_every=1, checkpoint_every=10**9)
            reset_peak(dev)
            sync(dev)
            t0 = time.perf_counter()
            out = train(cfg, Source(), Run(90), steps=steps, device=dev, log=print)
            sync(dev)
            per = [h["step_s"] for h in out["history"]][min(2, len(out["history"]) - 1):]  # after warm-up
            return record(a.out, "paper_tokenizer_train_step", {
                "batch": cfg.batch_size, "steps": out["step"], "median_step_s": float(np.median(per)),
                "iterations_per_s": 1.0 / float(np.median(per)), "peak_memory_gib": peak_gib(dev),
                "parameters": count_parameters(out["model"]), "wall_s": time.perf_counter() - t0,
                "note": "batch assembled on the CPU each step (make_batch), as pcfbench train does"})

        part("paper_tokenizer_train_step", tok_step, 90)

    if "wide" not in parts:
        record(a.out, "total_s", time.monotonic() - t_start)
        return
    # 3. the largest world model the lease allows, trained on the tiny tokenizer's windows
    train_w, test_w = load_windows(a.inputs, "train"), load_windows(a.inputs, "test")
    if a.smoke:
        train_w, test_w = ({k: v[:4] for k, v in w.items() if k != "n"} for w in (train_w, test_w))
    base = world_config_for(PAPER, TINY_TOKENIZER)  # the paper's widths on the tiny tokenizer's 64 x 64 codes
    if a.smoke:
        base = TINY.with_overrides(batch_size=2)
    record(a.out, "copy_test", copy_accuracy(test_w, base.n_past))
    record(a.out, "copy_train", copy_accuracy(train_w, base.n_past))

    def train_big():
        budget = min(a.train_budget, left() - 120) if not a.smoke else 5
        if a.wide_steps:
            t, steps = None, a.wide_steps
        else:
            torch.manual_seed(0)
            probe = WorldModel(base).to(dev)
            t = time_train_steps(probe, base, dev, base.batch_size, 5 if not a.smoke else 1, 2 if not a.smoke else 1)
            del probe
            steps = max(10, int(budget / t["median_step_s"]))
        cfg = base.with_overrides(name="paper-widths-tiny-tokens", warmup=max(1, min(200, steps // 10)),
                                  decay_steps=steps, max_steps=steps)
        torch.manual_seed(0)
        model = WorldModel(cfg).to(dev)
        reset_peak(dev)
        t0 = time.perf_counter()
        out = train_world(model, cfg, {"tokens": train_w["tokens"], "poses": train_w["poses"]}, D.COPILOT4D,
                          Run(budget + 30), steps=steps, seed=0, manifest_config={}, log=print)
        wall = time.perf_counter() - t0
        record(a.out, "trained_world_model", {
            "config": {k: v for k, v in cfg.to_dict().items()}, "parameters": count_parameters(model),
            "steps": out["step"], "steps_planned": steps, "wall_s": wall, "probe": t,
            "peak_memory_gib": peak_gib(dev), "windows": len(train_w["tokens"]), "history": out["history"]})
        return model, cfg

    got = part("trained_world_model", train_big, 200 if not a.smoke else 0)

    runs = []
    if got is not None:
        runs.append(("gpu", *got))
    tiny_pt = a.inputs / "tiny-copilot4d.pt"
    if tiny_pt.is_file():
        w = torch.load(tiny_pt, map_location="cpu", weights_only=True)
        tiny = WorldModel(world_config_for(TINY, TINY_TOKENIZER))
        tiny.load_state_dict({k[len("world."):]: v.float() for k, v in w.items() if k.startswith("world.")})
        runs.append(("tiny600", tiny.to(dev), tiny.cfg))

    # 4. forecast the harness's kitti-1s test samples, for copilot4d_replay.py to render and score
    samples = a.inputs / "samples-kitti-1s.npz"
    if samples.is_file() and runs:
        part("replay", lambda: record(a.out, "replay", replay(runs, samples, a.out, dev, smoke=a.smoke)), 20)

    # 5. judge them in token space
    # the test split first, the defaults (w = 2, top 3) first: what matters most survives a cut
    order = [(split, w, k) for split in ("test", "train") for w, k in ((2.0, 3), (0.0, 1))][:3]
    for split, w, k in order:
        for name, model, cfg in runs:
            win = test_w if split == "test" else train_w
            key = f"judge_{name}_{split}_w{w:g}_top{k}"
            part(key, lambda model=model, cfg=cfg, win=win, w=w, k=k, key=key: record(
                a.out, key, judge(model, cfg, win, dev, guidance=w, top_k=k, revise=True, seed=3)), 25)
    record(a.out, "total_s", time.monotonic() - t_start)


if __name__ == "__main__":
    main()
