"""CLI of the Copilot4D tokenizer: ``pcfbench train tokenizer``, ``pcfbench tokenize`` and
``pcfbench tokenizer-report``. Registered as the ``builtin-copilot4d`` entry point."""

from __future__ import annotations

import os
from pathlib import Path

import click

from pcfbench.hookspecs import hookimpl


def _dataset(spec: str):
    from pcfbench.config import parse_dataset_args
    from pcfbench.methods.copilot4d.data import open_dataset

    names, roots = parse_dataset_args((spec,))
    return open_dataset(names[0], roots.get(names[0]))


def _progress() -> bool:
    return not os.environ.get("PCFBENCH_NO_PROGRESS")


def _checkpoint(config: str, dataset_name: str, checkpoint: str | None) -> Path:
    from pcfbench.errors import PcfbenchError
    from pcfbench.methods.copilot4d.train import checkpoint_dir

    path = Path(checkpoint) if checkpoint else checkpoint_dir(config, dataset_name) / "last.pt"
    if not path.is_file():
        raise PcfbenchError(f"no tokenizer checkpoint at {path}: run `pcfbench train tokenizer --config {config} "
                            f"--dataset {dataset_name}` first")
    return path


def _skip_setting(model, adapter, ckpt: Path, step: int) -> dict:
    """The spatial-skipping threshold calibrated on training sweeps (cached next to the checkpoint)."""
    import json

    from pcfbench.methods.copilot4d.data import SweepSource
    from pcfbench.methods.copilot4d.evaluate import calibrate_skipping

    path = ckpt.with_name(ckpt.stem + "-skipping.json")
    if path.is_file():
        cached = json.loads(path.read_text())
        if cached.get("step") == step:
            return cached
    setting = calibrate_skipping(model, SweepSource(adapter, "train"))
    setting["step"] = step
    path.write_text(json.dumps(setting, indent=1))
    click.echo(f"spatial skipping calibrated on train sweeps: threshold {setting['threshold']}, noise {setting['noise']}")
    return setting


def _report(model, adapter, split: str, max_sweeps: int, reports: str | None, meta: dict, skip: dict | None = None) -> Path:
    from pcfbench.config import reports_dir
    from pcfbench.methods.copilot4d.data import SweepSource
    from pcfbench.methods.copilot4d.evaluate import evaluate_reconstruction, write_report

    result = evaluate_reconstruction(model, SweepSource(adapter, split), max_sweeps=max_sweeps, skip=skip)
    md, _ = write_report(result, meta, reports_dir(reports) / "copilot4d",
                         f"tokenizer-{model.cfg.name}-{adapter.name}-{split}")
    s = result.get("calibrated", result["skipping"])
    click.echo(f"reconstruction ({split}, {result['sweeps']} sweeps): L1 median {s['l1_median']:.3f} m, "
               f"L1 mean {s['l1_mean']:.3f} m, NFCD {s['chamfer_nf']:.3f}, CD {s['chamfer']:.3f}; "
               f"codebook usage {result['codebook_usage']:.1%}")
    click.echo(f"wrote {md}")
    return md


@hookimpl
def register_commands(cli):  # noqa: ANN001
    train_group = cli.commands.get("train")
    if train_group is None:
        @cli.group("train")
        def train_group() -> None:
            """Train learned components (tokenizers, world models)."""

    @train_group.command("tokenizer")
    @click.option("--config", "config_name", default="tiny", show_default=True, help="tiny or paper")
    @click.option("--dataset", "dataset_spec", required=True, help="NAME or NAME=ROOT of a registered dataset")
    @click.option("--split", default="train", show_default=True)
    @click.option("--steps", type=int, default=None, help="total steps (default: the config's max_steps)")
    @click.option("--max-minutes", type=float, default=None, help="stop (with a checkpoint) after this much time")
    @click.option("--fresh", is_flag=True, help="ignore an existing checkpoint instead of resuming")
    @click.option("--eval-split", default="val", show_default=True, help="split of the reconstruction report ('' to skip)")
    @click.option("--eval-sweeps", type=int, default=40, show_default=True)
    @click.option("--reports", default=None, help="reports folder (default ./reports)")
    @click.option("--seed", type=int, default=0)
    @click.option("--threads", type=int, default=1, show_default=True,
                  help="CPU threads (1 is fastest per CPU-second on a shared machine)")
    def train_tokenizer(config_name, dataset_spec, split, steps, max_minutes, fresh, eval_split, eval_sweeps, reports, seed,
                        threads):
        """Train the Copilot4D tokenizer (VQ-VAE with depth rendering); resumes from its checkpoint."""
        import torch

        from pcfbench.config import reports_dir
        from pcfbench.methods.copilot4d.config import get_config
        from pcfbench.methods.copilot4d.data import SweepSource
        from pcfbench.methods.copilot4d.train import checkpoint_dir, count_parameters, default_device, train, write_curve

        cfg = get_config(config_name)
        adapter = _dataset(dataset_spec)
        source = SweepSource(adapter, split)
        ckpt = checkpoint_dir(cfg.name, adapter.name) / "last.pt"
        device = default_device()
        click.echo(f"tokenizer {cfg.name}: {len(source)} {split} sweeps of {adapter.name}, device {device}, "
                   f"checkpoint {ckpt}")
        out = train(cfg, source, ckpt, steps=steps, max_minutes=max_minutes, resume=not fresh, device=device,
                    seed=seed, progress=_progress(), threads=threads, log=click.echo)
        stem = f"tokenizer-{cfg.name}-{adapter.name}"
        if out["history"]:
            csv_path, png = write_curve(out["history"], reports_dir(reports) / "copilot4d", f"{stem}-curve",
                                         cfg.codebook_size)
            click.echo(f"wrote {csv_path} and {png}")
        if eval_split:
            meta = {"config": cfg.name, "codebook_size": cfg.codebook_size, "tokens": f"{cfg.bev_tokens}x{cfg.bev_tokens}",
                    "parameters": count_parameters(out["model"]), "steps": out["step"],
                    "training_time_s": round(out["elapsed_s"], 1),
                    "training_cpu_s": round(out["cpu_s"], 1), "device": str(device),
                    "torch_threads": torch.get_num_threads(), "checkpoint": str(ckpt)}
            skip = _skip_setting(out["model"], adapter, ckpt, out["step"])
            _report(out["model"], adapter, eval_split, eval_sweeps, reports, meta, skip)

    @cli.command("tokenize")
    @click.option("--config", "config_name", default="tiny", show_default=True)
    @click.option("--dataset", "dataset_spec", required=True, help="NAME or NAME=ROOT")
    @click.option("--split", default="train", show_default=True)
    @click.option("--checkpoint", default=None, help="tokenizer checkpoint (default: the trained one in the cache)")
    @click.option("--out", "out_dir", default=None, help="default: <cache>/copilot4d/tokens/<dataset>-<config>/<split>")
    def tokenize(config_name, dataset_spec, split, checkpoint, out_dir):
        """Cache the BEV token maps of a dataset split for the world model."""
        from pcfbench.config import cache_dir
        from pcfbench.methods.copilot4d.evaluate import tokenize_split
        from pcfbench.methods.copilot4d.train import load_tokenizer

        adapter = _dataset(dataset_spec)
        model, _ = load_tokenizer(_checkpoint(config_name, adapter.name, checkpoint))
        out = Path(out_dir) if out_dir else cache_dir() / "copilot4d" / "tokens" / f"{adapter.name}-{config_name}" / split
        tokenize_split(model, adapter, split, out, log=click.echo)

    @cli.command("tokenizer-report")
    @click.option("--config", "config_name", default="tiny", show_default=True)
    @click.option("--dataset", "dataset_spec", required=True, help="NAME or NAME=ROOT")
    @click.option("--split", default="val", show_default=True)
    @click.option("--checkpoint", default=None)
    @click.option("--sweeps", type=int, default=40, show_default=True)
    @click.option("--reports", default=None)
    def tokenizer_report(config_name, dataset_spec, split, checkpoint, sweeps, reports):
        """Table-7-style reconstruction numbers (NFCD, L1 median/mean, CD) of a trained tokenizer."""
        from pcfbench.methods.copilot4d.train import count_parameters, load_tokenizer

        adapter = _dataset(dataset_spec)
        path = _checkpoint(config_name, adapter.name, checkpoint)
        model, ck = load_tokenizer(path)
        meta = {"config": model.cfg.name, "codebook_size": model.cfg.codebook_size,
                "tokens": f"{model.cfg.bev_tokens}x{model.cfg.bev_tokens}", "parameters": count_parameters(model),
                "steps": ck["step"], "training_time_s": round(ck.get("elapsed_s", 0.0), 1),
                "training_cpu_s": round(ck.get("cpu_s", 0.0), 1), "checkpoint": str(path)}
        _report(model, adapter, split, sweeps, reports, meta, _skip_setting(model, adapter, path, ck["step"]))
