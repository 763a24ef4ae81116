"""BEVWorld's ceiling (issue 44's first bar): a perfect prediction of the world model's target,
the ground-truth future latents, decoded and rendered exactly as ``bevworld`` renders its
forecast, scored by the harness beside ``bevworld-latent-copy`` (the same tokenizer: the last
past latent decoded and rendered at the future poses) and copy-last on the same samples
(Copilot4D's ``ceiling.score_beside``). If the ceiling does not beat the latent copy, no
training will. ``pcfbench bevworld-ceiling``.

The target of future sweep k (its points, ego returns removed), as ``bevworld`` trains on it:
``frame="own"``: encoded in its own sensor frame, decoded and rendered from its own origin;
``frame="t0"``: moved into the t=0 sensor frame, encoded there, decoded and rendered from its
sensor's position in that frame. (Standardising and de-standardising, which the world model's
target passes through, is the identity up to rounding and is left out.) Also per future step,
the root mean square of the standardised target's difference from the t=0 sweep's latent in
the same frame: how far the world model has to move the copy.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pcfbench.errors import PcfbenchError
from pcfbench.methods.bevworld import latent_copy as lc


def evaluate_ceiling(model, adapter, split: str, setting: str, *, frame: str = "own",
                     max_samples: int | None = None, log=print) -> dict:
    """The ceiling of ``bevworld`` on the tokenizer ``model`` (a ``LatentTokenizer``), beside
    ``bevworld-latent-copy`` and copy-last. Returns per-entry means (``means``), ``rows``,
    ``change`` (mean and per step), ``samples`` and ``sweeps``."""
    import torch

    from pcfbench.data import Forecast
    from pcfbench.methods.copilot4d.ceiling import score_beside
    from pcfbench.methods.copy_last import CopyLast

    if frame not in lc.FRAMES:
        raise PcfbenchError(f"ceiling frame {frame!r}: expected one of {', '.join(lc.FRAMES)}")
    model.eval()
    copy_last = CopyLast()
    change: list[list[float]] = []

    def ceiling(sample, builder, seq_name: str, ref: int):
        seq = builder.sequence(seq_name)
        stride = builder.setting.stride
        T_s0_ref = np.linalg.inv(sample.past_T_ref_sensor[-1])
        last = model.normalise(lc.encode_sweep(model, builder.points_sensor(seq, ref)))
        latents, frames, steps = [], [], []
        for k in range(sample.num_future):
            pts = builder.points_sensor(seq, ref + (k + 1) * stride)
            if frame == "t0":
                z = lc.encode_sweep(model, pts, T_s0_ref @ sample.future_T_ref_sensor[k])
                frames.append(T_s0_ref)
            else:
                z = lc.encode_sweep(model, pts)
                frames.append(np.linalg.inv(sample.future_T_ref_sensor[k]))
            steps.append(float(torch.sqrt(((model.normalise(z) - last) ** 2).mean())))
            latents.append(z)
        change.append(steps)
        return Forecast.from_depths(sample, lc.render_sample(model, latents, sample, frames))

    res = score_beside(adapter, split, setting, {
        "ceiling": ceiling,
        "bevworld-latent-copy": lambda sample, *_: lc.copy_forecast(model, sample.for_method()),
        "copy-last": lambda sample, *_: copy_last.forecast(sample.for_method())},
        max_samples=max_samples, log=log, label=f"bevworld ceiling ({frame})")
    ch = np.asarray(change, np.float64)
    return {"setting": setting, "split": split, "dataset": adapter.name, "frame": frame,
            "samples": res["samples"], "of_samples": res["of_samples"],
            "sweeps": len(res["rows"]["ceiling"]), "eval_s": res["eval_s"],
            "means": res["means"], "rows": res["rows"],
            "change": {"mean": float(ch.mean()), "per_step": [float(v) for v in ch.mean(axis=0)]}}


def write_ceiling(result: dict, meta: dict, out_dir: Path, stem: str) -> tuple[Path, Path]:
    """The ceiling as Markdown and CSV: its means, the latent copy's and copy-last's from the same
    loop, and the ratios, labelled as a bound that sees the future."""
    how = {"own": "encoded in its own sensor frame, decoded and rendered from its own origin",
           "t0": "moved into the t=0 sensor frame, encoded there, decoded and rendered from its sensor's position in "
                 "that frame"}[result["frame"]]
    ch = result["change"]
    head = [
        f"# BEVWorld: the world model's ceiling ({meta.get('config')} tokenizer, {result['dataset']} "
        f"{result['split']}, {result['setting']}, frame {result['frame']})",
        "",
        "**A bound, not a method: it sees the future.** Each ground-truth future sweep is " + how + ", as "
        "`bevworld` renders its forecast. `bevworld-latent-copy` (the same tokenizer) and copy-last are scored in "
        "the same loop on the same samples by the same registered metrics; means are flat over (sample, future "
        "sweep).",
        "",
        f"{result['samples']} samples, {result['sweeps']} future sweeps; evaluation took {result['eval_s']:.0f} s. "
        f"RMS of the standardised target's difference from the t=0 latent: {ch['mean']:.3f} on average "
        f"({', '.join(f'{v:.3f}' for v in ch['per_step'])} by future step).",
        "",
    ]
    from pcfbench.methods.copilot4d.ceiling import write_beside

    return write_beside(result, meta, out_dir, stem, copy="bevworld-latent-copy",
                        target="bevworld's target", head=head, issue=44)
