"""The token-copy baseline: the Copilot4D tokenizer as a trained method.

``fit`` trains the tokenizer (``train.train``, resumable through ``pcfbench train``).
``forecast`` tokenizes the last past sweep (t=0) in its sensor frame and renders those very
tokens with the decoder from each future sensor origin along that future sweep's query rays
(spatial skipping and the ``readout`` depth of ``options.RenderingOptions``): a world that
does not change, seen through the tokenizer. It isolates what a world model adds on top of
the tokenizer. Tiny checkpoints trained on synthetic-town-realistic (the default run's) and
on synthetic-town ship in ``checkpoints/`` (docs/copilot4d.md).
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, fields
from pathlib import Path

import numpy as np

from pcfbench.data import Forecast, Sample
from pcfbench.errors import PcfbenchError
from pcfbench.methods.copilot4d.options import RenderingOptions
from pcfbench.options import option
from pcfbench.training import Checkpoint, TrainedMethod, TrainingRun, TrainSource


@dataclass(frozen=True)
class TokenCopyOptions(RenderingOptions):
    config: str = option("tiny", help="tokenizer configuration: tiny (CPU scale), tiny-moved (tiny, trained also on "
                                      "sweeps seen from moved sensors), tiny-window (tiny, on sweeps moved as the "
                                      "world model's windows move them), tiny-views (tiny-window fine-tuned to give "
                                      "two views of one window the same codes) or paper (A.2.1 sizes)")
    steps: int = option(0, help="training steps (0: the configuration's max_steps)")
    seed: int = option(0, help="training seed (initialisation, batches, rays)")


class TokenCopy(TrainedMethod):
    """Copilot4D's tokenizer decoding the t=0 sweep's tokens at every future pose."""

    name = "copilot4d-token-copy"
    # the default run scores 8 evenly spaced samples of each cell (its 10-minute budget on a
    # 2-core CPU; docs/protocol.md, "The default run's subset"); --subset 0 or naming the method: all
    default_run_subset = 8
    # the default run scores the shipped tiny tokenizer's copy and, beside the world models, the
    # copy of theirs (tiny-window): each world model stands beside copying its own tokens
    default_run_options = ({}, {"config": "tiny-window"})
    version = "3"  # 2: the tiny grid covers the ROI ([-80, 80]^2 m); 3: tiny has 64 x 64 tokens (2.5 m)
    Options = TokenCopyOptions
    inference_options = tuple(f.name for f in fields(RenderingOptions))
    # the measurements behind it: docs/journal/copilot4d-2026-11.md, "Training times"
    training_time = "about 16 min for the tiny configuration on a 2-core CPU (1200 steps, 966 s measured)"

    def __init__(self, options: TokenCopyOptions | None = None) -> None:
        super().__init__(options)
        from pcfbench.methods.copilot4d.config import get_config
        from pcfbench.methods.copilot4d.evaluate import rendering_kwargs

        self.cfg = get_config(self.options.config)
        self.render = rendering_kwargs(self.options)
        self.model = None

    def training_steps(self) -> int:
        return self.options.steps or self.cfg.max_steps

    def fit(self, train_source: TrainSource, out_dir: Path, progress: TrainingRun) -> None:
        from pcfbench.methods.copilot4d.data import SweepSource
        from pcfbench.methods.copilot4d.train import default_device, train, write_curve

        device = default_device()  # CPU threads: the harness applied `pcfbench train --threads` (every CPU)
        source = SweepSource(train_source.adapter, train_source.split)
        progress.log(f"tokenizer {self.cfg.name}: {len(source)} {train_source.split} sweeps of "
                     f"{train_source.adapter.name}, device {device}, checkpoint {out_dir}")
        out = train(self.cfg, source, progress, steps=self.training_steps(), device=device, seed=self.options.seed,
                    log=progress.log, init=self.start_checkpoint(train_source, out_dir))
        if out["history"]:
            csv_path, png = write_curve(out["history"], Path(out_dir), "curve", self.cfg.codebook_size)
            progress.log(f"training curve: {csv_path} and {png}")

    def start_checkpoint(self, train_source: TrainSource, out_dir: Path) -> Checkpoint | None:
        """The complete checkpoint of ``cfg.init_from`` on the same training data that a training of
        this configuration starts from (None when it starts from random weights); a training
        resumed in ``out_dir`` goes on only from the one it started from."""
        import json

        from pcfbench.training import find_checkpoint, missing_checkpoint_message
        from pcfbench.training.checkpoints import MANIFEST

        if not self.cfg.init_from:
            return None
        spec = tokenizer_spec(self.cfg.init_from)
        ck = find_checkpoint(spec, train_source.train_on)
        if ck is None or not ck.manifest.get("complete"):
            raise PcfbenchError(f"tokenizer config {self.cfg.name!r} starts from the trained {self.cfg.init_from!r}: "
                                + missing_checkpoint_message(spec, train_source.train_on))
        manifest = Path(out_dir) / MANIFEST
        had = json.loads(manifest.read_text())["config"].get("init_from", {}) if manifest.is_file() else {}
        if had and had.get("weights_sha256") != ck.sha256:
            raise PcfbenchError(f"checkpoint {manifest} started from {self.cfg.init_from!r} weights "
                                f"{str(had.get('weights_sha256'))[:12]}, and {ck.manifest_path} is now {ck.sha256[:12]}: "
                                "rerun with --fresh")
        return ck

    def load(self, checkpoint: Checkpoint) -> None:
        from pcfbench.methods.copilot4d.train import config_from_dict, load_tokenizer

        recorded = config_from_dict(checkpoint.manifest.get("config", {}).get("tokenizer", {}))
        if recorded != self.cfg:
            raise PcfbenchError(f"checkpoint {checkpoint.manifest_path} was trained with another '{self.cfg.name}' "
                                "tokenizer configuration than this pcfbench defines; retrain it with --fresh")
        self.model = load_tokenizer(checkpoint)

    def forecast(self, sample: Sample) -> Forecast:
        import torch

        from pcfbench.methods.copilot4d.evaluate import render_queries, tokenize_sweep

        if self.model is None:
            raise PcfbenchError(f"{self.name}: no checkpoint loaded (the runner loads it; call load() first)")
        T_ref_s0 = sample.past_T_ref_sensor[-1]
        T_s0_ref = np.linalg.inv(T_ref_s0)
        R, t = T_s0_ref[:3, :3], T_s0_ref[:3, 3]
        points_s0 = (sample.past_points_ref[-1].astype(np.float64) @ R.T + t).astype(np.float32)
        codes = tokenize_sweep(self.model, points_s0)
        # Spatial skipping draws Logistic noise: seeded by the sample, so a forecast is reproducible.
        seed = int.from_bytes(hashlib.sha256(sample.sample_id.encode()).digest()[:8], "little")
        gen = torch.Generator().manual_seed(seed)
        return Forecast.from_depths(sample, render_queries(self.model, codes, sample, T_s0_ref, generator=gen,
                                                           execution=self.execution, **self.render))


def tokenizer_spec(config: str, steps: int = 0):
    """The resolved ``copilot4d-token-copy`` spec of tokenizer configuration ``config`` (and its
    ``steps`` option when set): the checkpoint a world model or an ``init_from`` start looks up."""
    from pcfbench.method import resolve_method

    opts = {} if config == "tiny" else {"config": config}
    if steps:
        opts["steps"] = str(steps)
    return resolve_method((TokenCopy.name, opts))
