"""OccWorld as a plugin (the ``builtin-occworld`` entry point): the tokenizer as the trained
method ``occworld-occ-copy`` (the last past occupancy's tokens, decoded and rendered at every
future pose) and the world model ``occworld`` on top of its checkpoint, and the command
``pcfbench occworld-ceiling``. Neither ships a checkpoint yet; the default run leaves them out
(docs/occworld.md)."""

from __future__ import annotations

from pcfbench.hookspecs import hookimpl


@hookimpl
def register_methods(register):  # noqa: ANN001
    register("occworld-occ-copy", "pcfbench.methods.occworld.occ_copy:OccCopy",
             "OccWorld's occupancy tokenizer decoding the t=0 occupancy's tokens from every future pose (trained)")
    register("occworld", "pcfbench.methods.occworld.forecaster:OccWorld",
             "OccWorld: occupancy tokenizer + spatio-temporal generative transformer, autoregressive (trained)")


@hookimpl
def register_commands(cli):  # noqa: ANN001
    import click

    @cli.command("occworld-ceiling")
    @click.option("--method", "method", default="occworld-occ-copy", show_default=True, metavar="NAME[:k=v,...]",
                  help="The tokenizer: its method spec, e.g. occworld-occ-copy:config=paper,frame=t0.")
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
    def occworld_ceiling(method, train_on, train_split, checkpoint, dataset_spec, split, setting, max_samples, reports):
        """OccWorld's ceiling: its training target for the ground-truth future (in the tokenizer's
        frame option), decoded and rendered as occworld renders, beside occworld-occ-copy and
        copy-last (it sees the future; never a method)."""
        from pcfbench.config import reports_dir
        from pcfbench.methods.copilot4d.plugin import _loaded, _open
        from pcfbench.methods.occworld.ceiling import evaluate_ceiling, write_ceiling
        from pcfbench.methods.occworld.occ_copy import OccCopy
        from pcfbench.methods.occworld.tokenizer import count_parameters

        m, ck = _loaded(method, OccCopy, "occworld-occ-copy[:options] (an OccWorld tokenizer)", train_on,
                        train_split, checkpoint)
        adapter = _open(dataset_spec)
        o = m.options
        res = evaluate_ceiling(m.model, adapter, split, setting, frame=o.frame, readout=o.readout,
                               max_samples=max_samples or None, log=click.echo)
        meta = {"config": m.cfg.name, "tokens": "x".join(map(str, m.cfg.token_grid)),
                "parameters": count_parameters(m.model), "trained_on": ck.train_on_label, "steps": ck.steps,
                "checkpoint": str(ck.manifest_path), "weights_sha256": ck.sha256,
                "regenerate": f"pcfbench occworld-ceiling --method {method} --dataset {dataset_spec} --split {split} "
                              f"--setting {setting} --samples {max_samples}"}
        md, csv_path = write_ceiling(res, meta, reports_dir(reports) / "occworld",
                                     f"ceiling-{m.cfg.name}-{ck.train_on['dataset']}-on-{adapter.name}-{split}-"
                                     f"{setting}-{o.frame}")
        c, cp = res["means"]["ceiling"], res["means"]["occworld-occ-copy"]
        click.echo(f"ceiling ({setting}, frame {o.frame}, {res['samples']} samples) / occworld-occ-copy: "
                   + ", ".join(f"{n} {c[n] / cp[n]:.2f}" for n in ("chamfer_nf", "l1_mean", "l1_median")))
        click.echo(f"wrote {md} and {csv_path}")
