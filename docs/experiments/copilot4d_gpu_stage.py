"""Stage the inputs of copilot4d_gpu.py in .gpu/ (ignored by git; carry it to the GPU machine).

Also the world model's inputs for synthetic-town's kitti-1s test samples (``samples-kitti-1s.npz``):
the GPU forecasts their future tokens, and ``copilot4d_replay.py`` renders and scores them here.

Needs the tiny tokenizer checkpoint trained on synthetic-town (``pcfbench train
copilot4d-token-copy --dataset synthetic-town``); copies the tiny copilot4d checkpoint's
weights if it is trained, and 8 real KITTI sweeps if ``--kitti`` names a KITTI sequence folder
(``.../sequences/00``). Run from the repository root with the project's environment.
"""

from __future__ import annotations

import argparse
import shutil
from pathlib import Path

import numpy as np
import torch

from pcfbench.errors import PcfbenchError
from pcfbench.method import resolve_method
from pcfbench.methods.copilot4d.forecaster import build_windows, window_cache_dir
from pcfbench.methods.copilot4d.train import load_tokenizer
from pcfbench.training import find_checkpoint, open_training_data


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--out", type=Path, default=Path(".gpu"))
    ap.add_argument("--kitti", type=Path, help="a KITTI sequence folder holding velodyne/*.bin")
    a = ap.parse_args()
    a.out.mkdir(exist_ok=True)
    train = open_training_data("synthetic-town", "train")
    tok_ck = find_checkpoint(resolve_method("copilot4d-token-copy"), train.train_on)
    if tok_ck is None:
        raise PcfbenchError("no copilot4d-token-copy checkpoint for synthetic-town: "
                            "pcfbench train copilot4d-token-copy --dataset synthetic-town")
    tokenizer = load_tokenizer(tok_ck, torch.device("cpu"))
    print(f"tokenizer {tok_ck.dir} (sha256 {tok_ck.sha256[:12]})")
    for split, every in (("train", 2), ("test", 1)):  # train: the training windows; test: every sweep
        src = train if split == "train" else open_training_data("synthetic-town", split)
        cache = window_cache_dir(tok_ck.sha256, train.train_on.key) if split == "train" else None
        for stride in (2, 6):
            w = build_windows(tokenizer, src.adapter, split, 5, 5, (stride,), every, cache)
            np.savez_compressed(a.out / f"{split}-s{stride}.npz", tokens=w["tokens"], poses=w["poses"])
            print(f"{split} stride {stride}: {len(w['tokens'])} windows")
    world = find_checkpoint(resolve_method("copilot4d"), train.train_on)
    if world is not None:
        shutil.copyfile(world.weights_path, a.out / "tiny-copilot4d.pt")
        print(f"tiny copilot4d weights: {world.weights_path}")
    # the world model's inputs for every kitti-1s sample of the test split, exactly as the
    # copilot4d method computes them (Copilot4D.world_inputs), for the GPU to forecast
    from pcfbench.methods.copilot4d.forecaster import Copilot4D
    from pcfbench.plugins import get_setting
    from pcfbench.protocol import SampleBuilder

    method = Copilot4D()
    method.tokenizer = tokenizer
    test = open_training_data("synthetic-town", "test")
    builder = SampleBuilder(test.adapter, get_setting("kitti-1s"))
    ids, toks, poses = [], [], []
    for key in builder.sample_keys("test"):
        sample, _ = builder.build(*key)
        seq, rel, _ = method.world_inputs(sample.for_method())
        ids.append(sample.sample_id)
        toks.append(seq.numpy().astype(np.int16))
        poses.append(rel.numpy())
    np.savez_compressed(a.out / "samples-kitti-1s.npz", sample_ids=np.array(ids), tokens=np.stack(toks),
                        poses=np.stack(poses), tokenizer_sha256=np.array(tok_ck.sha256))
    print(f"{len(ids)} kitti-1s test samples' world-model inputs")
    if a.kitti:
        clouds = []
        for f in sorted((a.kitti / "velodyne").glob("*.bin"))[:8]:
            p = np.fromfile(f, np.float32).reshape(-1, 4)[:, :3]
            clouds.append(p[np.linalg.norm(p[:, :2], axis=1) > 3.0])  # the car's own returns out, roughly
        np.savez(a.out / "kitti8.npz", points=np.concatenate(clouds), offsets=np.cumsum([0] + [len(c) for c in clouds]))
        print(f"{len(clouds)} KITTI sweeps, {[len(c) for c in clouds]} points")


if __name__ == "__main__":
    main()
