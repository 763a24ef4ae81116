"""OccWorld as a plugin (the ``builtin-occworld`` entry point): the tokenizer as the trained
method ``occworld-occ-copy`` (the last past occupancy's tokens, decoded and rendered at every
future pose) and the world model ``occworld`` on top of its checkpoint, and the command
``pcfbench occworld-ceiling``. Both ship their ``tiny`` checkpoints and stand on the default
leaderboard (docs/occworld.md)."""

from __future__ import annotations

from pcfbench.hookspecs import hookimpl


@hookimpl
def register_methods(register):  # noqa: ANN001
    register("occworld-occ-copy", "pcfbench.methods.occworld.occ_copy:OccCopy",
             "OccWorld's occupancy tokenizer decoding the t=0 occupancy's tokens from every future pose (trained)")
    register("occworld", "pcfbench.methods.occworld.forecaster:OccWorld",
             "OccWorld: occupancy tokenizer + spatio-temporal generative transformer, autoregressive (trained)")


def _non_default(options, skip=()) -> list[str]:
    """``name`` + value of each option of ``options`` that differs from its default (``tokens100``,
    ``surface-mean``), in field order, those in ``skip`` left out."""
    from dataclasses import fields

    out = []
    for f in fields(options):
        value = getattr(options, f.name)
        if f.name not in skip and value != f.default:
            out.append(f"{f.name}-{value}" if isinstance(value, str) else f"{f.name}{value}")
    return out


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
    @click.option("--perfect", is_flag=True,
                  help="No tokenizer: the labels are the tokens and decode to certain occupancy (the bound of the "
                       "grid and the rendering alone; needs no checkpoint).")
    @click.option("--grid", default=None, metavar="NXxNYxNZ", help="With --perfect: another grid over the ROI.")
    @click.option("--surface", type=click.Choice(["none", "front", "mean"]), default=None,
                  help="With --perfect: render through one sub-voxel plane per voxel at the front (or mean) of its "
                       "returns (the labels' offsets; docs/occworld.md), or none: the method's readout of the "
                       "occupancy alone. Default: the method's surface option with readout=surface, else none.")
    @click.option("--reports", default=None)
    def occworld_ceiling(method, train_on, train_split, checkpoint, dataset_spec, split, setting, max_samples, perfect,
                         grid, surface, reports):
        """OccWorld's ceiling: its training target for the ground-truth future (in the tokenizer's
        frame option), decoded and rendered as occworld renders, beside occworld-occ-copy and
        copy-last (it sees the future; never a method)."""
        from dataclasses import replace

        from pcfbench.config import reports_dir
        from pcfbench.errors import PcfbenchError
        from pcfbench.method import resolve_method
        from pcfbench.methods.copilot4d.plugin import _loaded, _open
        from pcfbench.methods.occworld.ceiling import LabelTokens, evaluate_ceiling, write_ceiling
        from pcfbench.methods.occworld.occ_copy import OccCopy
        from pcfbench.methods.occworld.tokenizer import count_parameters

        regenerate = (f"pcfbench occworld-ceiling --method {method} --dataset {dataset_spec} --split {split} "
                      f"--setting {setting} --samples {max_samples}")
        if grid and not perfect:
            raise PcfbenchError("--grid: only with --perfect (a trained tokenizer has its own grid)")
        if surface is not None and not perfect:
            raise PcfbenchError("--surface: only with --perfect (a trained tokenizer renders the planes it decodes, "
                                "readout=surface)")
        if perfect:
            spec = resolve_method(method)
            if not issubclass(spec.cls, OccCopy):
                raise PcfbenchError(f"--method {method!r}: expected occworld-occ-copy[:options]")
            o, cfg = spec.options, spec.create().cfg
            if surface is None:
                surface = o.surface if o.readout == "surface" else "none"
            if grid:
                try:
                    dims = tuple(int(v) for v in grid.lower().split("x"))
                except ValueError:
                    dims = ()
                if len(dims) != 3 or min(dims) < 1:
                    raise PcfbenchError(f"--grid {grid!r}: expected NXxNYxNZ, e.g. 400x400x24")
                cfg = replace(cfg, name=f"{cfg.name}-{grid}", dims=dims, ch_mult=(1,))
            model, label = LabelTokens(cfg), "perfect"
            meta = {"config": f"perfect (the labels as tokens, {cfg.name} grid)", "grid": "x".join(map(str, cfg.dims)),
                    "regenerate": regenerate + " --perfect" + (f" --grid {grid}" if grid else "")
                    + (f" --surface {surface}" if surface != "none" else "")}
        else:
            surface = "none"
            m, ck = _loaded(method, OccCopy, "occworld-occ-copy[:options] (an OccWorld tokenizer)", train_on,
                            train_split, checkpoint)
            # the tokenizer's non-default options name its files (the configuration and frame already
            # do): never those of the default's
            label = "-".join([m.cfg.name, *_non_default(m.options, skip=("config", "frame")), ck.train_on["dataset"]])
            o, cfg, model = m.options, m.cfg, m.model
            meta = {"config": cfg.name, "tokens": "x".join(map(str, cfg.token_grid)),
                    "parameters": count_parameters(model), "trained_on": ck.train_on_label, "steps": ck.steps,
                    "checkpoint": str(ck.manifest_path), "weights_sha256": ck.sha256, "regenerate": regenerate}
        adapter = _open(dataset_spec)
        # perfect occupancy without planes: the middle of the first occupied voxel (what expected and
        # threshold both give for certain occupancy)
        readout = "threshold" if perfect and o.readout == "surface" else o.readout
        res = evaluate_ceiling(model, adapter, split, setting, frame=o.frame, readout=readout, surface=surface,
                               max_samples=max_samples or None, log=click.echo)
        md, csv_path = write_ceiling(res, meta, reports_dir(reports) / "occworld",
                                     f"ceiling-{label}-{'x'.join(map(str, cfg.dims))}-on-{adapter.name}-{split}-"
                                     f"{setting}-{o.frame}" + (f"-surface-{surface}" if surface != "none" else ""))
        c, cp = res["means"]["ceiling"], res["means"]["occworld-occ-copy"]
        click.echo(f"ceiling ({setting}, frame {o.frame}, {res['samples']} samples) / occworld-occ-copy: "
                   + ", ".join(f"{n} {c[n] / cp[n]:.2f}" for n in ("chamfer_nf", "l1_mean", "l1_median")))
        click.echo(f"wrote {md} and {csv_path}")
