"""BEVWorld as a plugin (the ``builtin-bevworld`` entry point): the tokenizer as the trained
method ``bevworld-latent-copy`` (the last past sweep's latent, decoded and rendered at every
future pose) and the world model ``bevworld`` on top of its checkpoint, and the command
``pcfbench bevworld-ceiling``. Neither ships a
checkpoint yet; the default run leaves them out (docs/bevworld.md)."""

from __future__ import annotations

from pcfbench.hookspecs import hookimpl


@hookimpl
def register_methods(register):  # noqa: ANN001
    register("bevworld-latent-copy", "pcfbench.methods.bevworld.latent_copy:LatentCopy",
             "BEVWorld's LiDAR tokenizer rendering the t=0 sweep's continuous BEV latent from every future pose "
             "(trained)")
    register("bevworld", "pcfbench.methods.bevworld.forecaster:BevWorld",
             "BEVWorld: continuous BEV latent tokenizer + latent diffusion transformer, DDIM (trained)")


@hookimpl
def register_commands(cli):  # noqa: ANN001
    import click

    @cli.command("bevworld-ceiling")
    @click.option("--method", "method", default="bevworld-latent-copy", show_default=True, metavar="NAME[:k=v,...]",
                  help="The tokenizer: its method spec, e.g. bevworld-latent-copy:config=paper,frame=t0.")
    @click.option("--train-on", default=None, metavar="NAME[=ROOT]",
                  help="The tokenizer trained on this dataset (default: synthetic-town-realistic).")
    @click.option("--train-split", default="train", show_default=True)
    @click.option("--checkpoint", type=click.Path(exists=True), default=None,
                  help="Checkpoint folder or file (default: the one trained on --train-on).")
    @click.option("--dataset", "dataset_spec", required=True, help="NAME or NAME=ROOT of the samples")
    @click.option("--split", default="test", show_default=True)
    @click.option("--setting", default="kitti-1s", show_default=True, help="The protocol setting, e.g. kitti-3s.")
    @click.option("--samples", "max_samples", type=int, default=0, show_default=True,
                  help="This many evenly spaced samples (0: all).")
    @click.option("--reports", default=None)
    def bevworld_ceiling(method, train_on, train_split, checkpoint, dataset_spec, split, setting, max_samples,
                         reports):
        """BEVWorld's ceiling: the ground-truth future latents (in the tokenizer's frame option),
        decoded and rendered as bevworld renders, beside bevworld-latent-copy and copy-last (it
        sees the future; never a method)."""
        from pcfbench.config import reports_dir
        from pcfbench.methods.bevworld.ceiling import evaluate_ceiling, write_ceiling
        from pcfbench.methods.bevworld.latent_copy import LatentCopy
        from pcfbench.methods.bevworld.tokenizer import count_parameters
        from pcfbench.methods.copilot4d.plugin import _loaded, _open

        m, ck = _loaded(method, LatentCopy, "bevworld-latent-copy[:options] (a BEVWorld tokenizer)", train_on,
                        train_split, checkpoint)
        o, cfg = m.options, m.cfg
        meta = {"config": cfg.name, "latent": f"{cfg.latent_grid}x{cfg.latent_grid}x{cfg.latent_channels}",
                "parameters": count_parameters(m.model), "trained_on": ck.train_on_label, "steps": ck.steps,
                "checkpoint": str(ck.manifest_path), "weights_sha256": ck.sha256,
                "regenerate": f"pcfbench bevworld-ceiling --method {method} --dataset {dataset_spec} --split {split} "
                              f"--setting {setting} --samples {max_samples}"}
        adapter = _open(dataset_spec)
        res = evaluate_ceiling(m.model, adapter, split, setting, frame=o.frame, max_samples=max_samples or None,
                               log=click.echo)
        md, csv_path = write_ceiling(res, meta, reports_dir(reports) / "bevworld",
                                     f"ceiling-{cfg.name}-{ck.train_on['dataset']}-on-{adapter.name}-{split}-"
                                     f"{setting}-{o.frame}")
        c, lcp = res["means"]["ceiling"], res["means"]["bevworld-latent-copy"]
        click.echo(f"ceiling ({setting}, frame {o.frame}, {res['samples']} samples) / bevworld-latent-copy: "
                   + ", ".join(f"{n} {c[n] / lcp[n]:.2f}" for n in ("chamfer_nf", "l1_mean", "l1_median")))
        click.echo(f"wrote {md} and {csv_path}")
