"""Render and score, here, the future tokens a GPU forecast for synthetic-town's kitti-1s test
samples (``copilot4d_gpu.py --parts wide`` writes ``replay-tokens.npz``), beside copy-last and
copilot4d-token-copy, every sample scored by the harness's own ``score_sample`` with every
default metric: an experiment, not a leaderboard cell (docs/copilot4d.md, "On a GPU").

Each replayed run is rendered exactly as the copilot4d method renders its own tokens
(``Copilot4D.forecast``: the token-copy checkpoint's tokenizer, the same rendering options and
per-sample seeds); only where the tokens come from differs.

    .venv/bin/python docs/experiments/copilot4d_replay.py REPLAY_TOKENS.npz [--out docs/results/copilot4d/...]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from pcfbench.errors import PcfbenchError
from pcfbench.method import resolve_method
from pcfbench.methods.copilot4d.forecaster import Copilot4D
from pcfbench.metrics.base import score_sample
from pcfbench.plugins import get_plugins
from pcfbench.plugins import get_setting
from pcfbench.protocol import SampleBuilder, sample_id
from pcfbench.running.runner import default_metrics
from pcfbench.training import find_checkpoint, open_training_data
from pcfbench.protocol.validate import validate_forecast


class Replay(Copilot4D):
    """copilot4d's rendering of future tokens that were forecast elsewhere."""

    name = "copilot4d-replay"

    def __init__(self, tokenizer, codes: dict[str, np.ndarray]) -> None:
        super().__init__()
        self.tokenizer, self.codes, self.world = tokenizer, codes, "replayed"

    def forecast_tokens(self, sample):
        T_s0_ref = np.linalg.inv(sample.past_T_ref_sensor[-1])
        codes = self.codes[sample.sample_id]
        if len(codes) != sample.num_future:
            raise PcfbenchError(f"sample {sample.sample_id}: {len(codes)} replayed future frames, "
                                f"expected {sample.num_future}")
        return [torch.from_numpy(c.astype(np.int64)) for c in codes], T_s0_ref @ sample.future_T_ref_sensor, T_s0_ref


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("tokens", type=Path)
    ap.add_argument("--out", type=Path, help="write the per-method means as JSON here")
    ap.add_argument("--limit", type=int, default=0, help="the first N samples only")
    a = ap.parse_args()
    torch.set_num_threads(2)
    z = np.load(a.tokens)
    ids = [str(s) for s in z["sample_ids"]]
    train = open_training_data("synthetic-town", "train", progress=False)
    tok_spec = resolve_method("copilot4d-token-copy")
    tok_ck = find_checkpoint(tok_spec, train.train_on)
    if tok_ck is None or tok_ck.sha256 != str(z["tokenizer_sha256"]):
        raise PcfbenchError(f"{a.tokens} was forecast on the tokens of tokenizer {str(z['tokenizer_sha256'])[:12]}; "
                            f"the local copilot4d-token-copy checkpoint is {tok_ck and tok_ck.sha256[:12]}")
    token_copy = tok_spec.create()
    token_copy.load(tok_ck)
    methods = {"copy-last": resolve_method("copy-last").create(), "copilot4d-token-copy": token_copy}
    for run in [k for k in z.files if k not in ("sample_ids", "tokenizer_sha256")]:
        methods[f"replay {run}"] = Replay(token_copy.model, dict(zip(ids, z[run])))
    plugins = get_plugins()
    metrics = [plugins.metrics.get(m) for m in default_metrics(plugins)]
    test = open_training_data("synthetic-town", "test", progress=False)
    builder = SampleBuilder(test.adapter, get_setting("kitti-1s"))
    keys = builder.sample_keys("test")
    if [sample_id(s, i) for s, i in keys[: len(ids)]] != ids:  # the GPU forecast them in the builder's order
        raise PcfbenchError(f"{a.tokens} holds other samples than synthetic-town's kitti-1s test samples")
    keys = keys[: min(len(ids), a.limit or len(ids))]
    rows: dict[str, list[dict]] = {m: [] for m in methods}
    for key in tqdm(keys, desc="samples"):
        sample, truth = builder.build(*key)
        for name, method in methods.items():
            forecast = validate_forecast(sample, method.forecast(sample.for_method()))
            rows[name].extend(score_sample(sample, truth, forecast, metrics))
    names = [m.name for m in metrics]
    means = {m: {n: float(np.nanmean([r[n] for r in rs])) for n in names} | {"sweeps": len(rs)}
             for m, rs in rows.items()}
    cols = ["chamfer_nf", "l1_mean", "l1_median"] + [n for n in names if n not in ("chamfer_nf", "l1_mean", "l1_median")]
    print("| method | " + " | ".join(cols) + " |\n|---|" + "---|" * len(cols))
    for m, v in means.items():
        print(f"| {m} | " + " | ".join(f"{v[c]:.4f}" for c in cols) + " |")
    if a.out:
        a.out.write_text(json.dumps({"tokens": str(a.tokens), "samples": len(keys), "means": means}, indent=1))


if __name__ == "__main__":
    main()
