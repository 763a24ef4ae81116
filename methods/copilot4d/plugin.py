"""Copilot4D as a plugin (the ``builtin-copilot4d`` entry point): the token-copy baseline
``copilot4d-token-copy`` (a trained method: ``pcfbench train copilot4d-token-copy --dataset
NAME``), the world model ``copilot4d`` and its MaskGIT variant ``copilot4d-maskgit``
(trained methods on top of that tokenizer's checkpoint), and the tokenizer's commands ``pcfbench tokenize`` (cache BEV token maps for the
world model), ``pcfbench tokenizer-report`` (Table 7's reconstruction numbers) and ``pcfbench world-report``
(a world model's forecast tokens, changed and unchanged apart) and ``pcfbench world-changes``
(what its changes are worth, beside bounds that see the future); the first two take
the trained checkpoint the way ``pcfbench run`` does (``--train-on`` or ``--checkpoint``)."""

from __future__ import annotations

from pathlib import Path

import click

from pcfbench.hookspecs import hookimpl

TOKENIZER = "copilot4d-token-copy"


@hookimpl
def register_methods(register):  # noqa: ANN001
    register(TOKENIZER, "pcfbench.methods.copilot4d.token_copy:TokenCopy",
             "Copilot4D tokenizer decoding the t=0 sweep's tokens from every future pose (trained)")
    register("copilot4d", "pcfbench.methods.copilot4d.forecaster:Copilot4D",
             "Copilot4D world model: tokenizer + discrete diffusion with guidance, autoregressive (trained)")
    register("copilot4d-maskgit", "pcfbench.methods.copilot4d.forecaster:Copilot4DMaskGIT",
             "Copilot4D world model trained and sampled as MaskGIT (Table 4's ablation; trained)")


def _loaded(method: str, cls: type, expected: str, train_on: str | None, train_split: str, checkpoint: str | None):
    """The method of spec ``method`` (a subclass of ``cls``, else one error saying ``expected``)
    with its checkpoint loaded, and that checkpoint (``--checkpoint``, else the one trained on
    ``train_on``'s ``train_split``)."""
    from pcfbench.errors import PcfbenchError
    from pcfbench.method import resolve_method
    from pcfbench.training import checkpoint_for

    spec = resolve_method(method)
    if not issubclass(spec.cls, cls):
        raise PcfbenchError(f"--method {method!r}: expected {expected}")
    ck = checkpoint_for(spec, checkpoint=checkpoint, train_on=train_on, split=train_split)
    m = spec.create()
    m.load(ck)
    return m, ck


def _tokenizer(method: str, train_on: str | None, train_split: str, checkpoint: str | None):
    """The trained tokenizer of ``method`` (a ``copilot4d-token-copy[:opts]`` spec) and its checkpoint."""
    from pcfbench.methods.copilot4d.token_copy import TokenCopy

    m, ck = _loaded(method, TokenCopy, f"{TOKENIZER}[:options] (a Copilot4D tokenizer)", train_on, train_split,
                    checkpoint)
    return m.model, ck


def spec_options(method: str):
    """The typed options of a ``copilot4d-token-copy[:opts]`` spec."""
    from pcfbench.method import resolve_method

    return resolve_method(method).options


def _checkpoint_options(default: str, what: str, method_help: str):
    """The options that pick a trained method and its checkpoint, as ``pcfbench run`` picks them:
    ``--method`` (default ``default``), ``--train-on``, ``--train-split``, ``--checkpoint``."""
    def add(f):
        f = click.option("--checkpoint", type=click.Path(exists=True), default=None,
                         help="Checkpoint folder or file (default: the one trained on --train-on).")(f)
        f = click.option("--train-split", default="train", show_default=True)(f)
        f = click.option("--train-on", default=None, metavar="NAME[=ROOT]",
                         help=f"The {what} trained on this dataset (default: synthetic-town-realistic).")(f)
        return click.option("--method", "method", default=default, show_default=True, metavar="NAME[:k=v,...]",
                            help=method_help)(f)
    return add


_tokenizer_options = _checkpoint_options(TOKENIZER, "tokenizer",
                                         "Which tokenizer: its method spec, e.g. copilot4d-token-copy:config=paper.")
_world_options = _checkpoint_options("copilot4d", "checkpoint",
                                     "The world model: copilot4d or copilot4d-maskgit, with its options.")


def _open(spec: str):
    from pcfbench.training import open_training_data

    # any split: open_training_data checks it exists; the adapter is what we need
    return open_training_data(spec, _any_split(spec)).adapter


def _any_split(spec: str) -> str:
    from pcfbench import config
    from pcfbench.plugins import get_plugins

    names, _ = config.parse_dataset_args((spec,))
    return get_plugins().datasets.get(names[0]).default_split


@hookimpl
def register_commands(cli):  # noqa: ANN001
    _world_report_command(cli)
    _world_changes_command(cli)

    @cli.command("tokenize")
    @_tokenizer_options
    @click.option("--dataset", "dataset_spec", required=True, help="NAME or NAME=ROOT of the sweeps to tokenize")
    @click.option("--split", default="train", show_default=True)
    @click.option("--out", "out_dir", default=None,
                  help="default: <cache>/copilot4d/tokens/<dataset>-<tokenizer sha256[:12]>/<split>")
    def tokenize(method, train_on, train_split, checkpoint, dataset_spec, split, out_dir):
        """Cache the BEV token maps of a dataset split for the world model."""
        from pcfbench.config import cache_dir
        from pcfbench.methods.copilot4d.evaluate import tokenize_split

        model, ck = _tokenizer(method, train_on, train_split, checkpoint)
        adapter = _open(dataset_spec)
        out = Path(out_dir) if out_dir else cache_dir() / "copilot4d" / "tokens" / f"{adapter.name}-{ck.sha256[:12]}" / split
        tokenize_split(model, adapter, split, out, log=click.echo)

    @cli.command("tokenizer-report")
    @_tokenizer_options
    @click.option("--dataset", "dataset_spec", required=True, help="NAME or NAME=ROOT of the sweeps to reconstruct")
    @click.option("--split", default="val", show_default=True)
    @click.option("--sweeps", type=int, default=40, show_default=True)
    @click.option("--reports", default=None)
    @click.option("--ceiling", "ceiling_setting", default=None, metavar="SETTING",
                  help="Also the world model's ceiling on SETTING (e.g. kitti-1s) of --split: its training target "
                       "for the ground-truth future, rendered as copilot4d renders, beside copilot4d-token-copy and "
                       "copy-last (it sees the future; never a method).")
    @click.option("--frame", type=click.Choice(["t0", "own"]), multiple=True, show_default=True,
                  default=("t0", "own"),
                  help="Ceiling: the frame the target is tokenized in (t0: moved into the t=0 sensor frame; own: "
                       "each future sweep in its own sensor frame); repeat for several.")
    @click.option("--ceiling-samples", type=int, default=0, show_default=True,
                  help="Ceiling: this many evenly spaced samples (0: all).")
    def tokenizer_report(method, train_on, train_split, checkpoint, dataset_spec, split, sweeps, reports,
                         ceiling_setting, frame, ceiling_samples):
        """Table-7-style reconstruction numbers (NFCD, L1 median/mean, CD) of a trained tokenizer,
        scored by the registered metrics (--sweeps 0: none); with --ceiling, the world model's
        ceiling beside copilot4d-token-copy and copy-last, in each --frame."""
        from pcfbench.config import reports_dir
        from pcfbench.methods.copilot4d.data import SweepSource
        from pcfbench.methods.copilot4d.evaluate import (calibrate_skipping, evaluate_reconstruction, rendering_kwargs,
                                                         write_report)
        from pcfbench.methods.copilot4d.train import count_parameters

        model, ck = _tokenizer(method, train_on, train_split, checkpoint)
        adapter = _open(dataset_spec)
        train_adapter = _open(ck.train_on["dataset"] + (f"={ck.train_on['root']}" if ck.train_on.get("root") else ""))
        render = rendering_kwargs(spec_options(method))
        meta = {"config": model.cfg.name, "codebook_size": model.cfg.codebook_size,
                "tokens": f"{model.cfg.bev_tokens}x{model.cfg.bev_tokens}", "parameters": count_parameters(model),
                "trained_on": ck.train_on_label, "steps": ck.steps, "training_time_s": ck.manifest.get("wall_s"),
                "training_cpu_s": ck.manifest.get("cpu_s"), "device": ck.manifest.get("device"),
                "checkpoint": str(ck.manifest_path), "weights_sha256": ck.sha256}
        if sweeps > 0:
            skip = calibrate_skipping(model, SweepSource(train_adapter, ck.train_on["split"]))
            click.echo(f"spatial skipping calibrated on {ck.train_on_label} sweeps: threshold {skip['threshold']}, "
                       f"noise {skip['noise']}")
            result = evaluate_reconstruction(model, SweepSource(adapter, split), max_sweeps=sweeps, skip=skip,
                                             render=render)
            md, _ = write_report(result, meta, reports_dir(reports) / "copilot4d",
                                 f"tokenizer-{model.cfg.name}-{ck.train_on['dataset']}-on-{adapter.name}-{split}")
            s = result.get("method", result["skipping"])
            click.echo(f"reconstruction ({split}, {result['sweeps']} sweeps): L1 median {s['l1_median']:.3f} m, "
                       f"L1 mean {s['l1_mean']:.3f} m, NFCD {s['chamfer_nf']:.3f}, CD {s['chamfer']:.3f}; "
                       f"codebook usage {result['codebook_usage']:.1%}")
            click.echo(f"wrote {md}")
        for fr in frame if ceiling_setting else ():
            from pcfbench.methods.copilot4d.ceiling import evaluate_ceiling, write_ceiling

            res = evaluate_ceiling(model, adapter, split, ceiling_setting, frame=fr, **render,
                                   max_samples=ceiling_samples or None, log=click.echo)
            meta["regenerate"] = (f"pcfbench tokenizer-report --method {method} --dataset {dataset_spec} "
                                  f"--split {split} --sweeps 0 --ceiling {ceiling_setting} --frame {fr} "
                                  f"--ceiling-samples {ceiling_samples}")
            md, csv_path = write_ceiling(res, meta, reports_dir(reports) / "copilot4d",
                                         f"ceiling-{model.cfg.name}-{ck.train_on['dataset']}-on-{adapter.name}-"
                                         f"{split}-{ceiling_setting}-{fr}")
            o, tc = res["means"]["ceiling"], res["means"]["copilot4d-token-copy"]
            click.echo(f"ceiling ({ceiling_setting}, frame {fr}, {res['samples']} samples) / token-copy: "
                       + ", ".join(f"{n} {o[n] / tc[n]:.2f}" for n in ("chamfer_nf", "l1_mean", "l1_median")))
            click.echo(f"wrote {md} and {csv_path}")


def _world_report_command(cli):  # noqa: ANN001
    @cli.command("world-report")
    @_world_options
    @click.option("--dataset", "dataset_spec", required=True, help="NAME or NAME=ROOT of the held-out windows")
    @click.option("--split", default="test", show_default=True)
    @click.option("--windows", "max_windows", type=int, default=12, show_default=True,
                  help="Evenly spaced windows per stride for the forecast, per set of windows for the "
                       "objective (0: all).")
    @click.option("--objective-draws", type=click.IntRange(min=0), default=0, show_default=True,
                  help="Also score the training objective (loss and accuracy on changed and unchanged tokens) "
                       "on this many corruptions of each held-out window and of as many of the windows the "
                       "model trained on (0: not).")
    @click.option("--forecast/--no-forecast", default=True, show_default=True,
                  help="Forecast and score the future tokens, decoded as the method decodes (Algorithm 2, or one_pass).")
    @click.option("--reports", default=None)
    def world_report(method, train_on, train_split, checkpoint, dataset_spec, split, max_windows, objective_draws,
                     forecast, reports):
        """A world model's forecast tokens on held-out windows against the real future's tokens,
        apart on the tokens that changed since the last past frame and those that did not; with
        --objective-draws, its training objective there and on the windows it trained on."""
        from pcfbench.config import reports_dir
        from pcfbench.errors import PcfbenchError
        from pcfbench.methods.copilot4d.forecaster import Copilot4D, build_windows, window_cache_dir
        from pcfbench.methods.copilot4d.token_report import (curve_tail, objective_report, objective_shares, shares,
                                                             world_token_report, write_objective_report,
                                                             write_token_report)
        from pcfbench.training import open_training_data

        if not forecast and not objective_draws:
            raise PcfbenchError("--no-forecast without --objective-draws: nothing to report")
        m, ck = _loaded(method, Copilot4D, "copilot4d or copilot4d-maskgit[:options]", train_on, train_split,
                        checkpoint)
        cfg, opts = m.world_cfg, m.options
        if objective_draws and m.stride_networks:  # the objective scores one network on windows of every stride
            raise PcfbenchError(f"--objective-draws scores one network, and {method} holds one per stride: name each "
                                "part (the training of its options without stride_models, or with strides=S)")

        def windows_of(source, split):
            return build_windows(m.tokenizer, source.adapter, split, cfg.n_past, cfg.n_future, tuple(opts.strides),
                                 opts.anchor_every,
                                 window_cache_dir(ck.manifest["config"]["tokenizer_sha256"], source.train_on.key),
                                 log=click.echo, frame=opts.frame)

        source = open_training_data(dataset_spec, split, split_option="--split {}")
        windows = windows_of(source, split)
        regenerate = (f"pcfbench world-report --method {method} --dataset {dataset_spec} --split {split} "
                      f"--windows {max_windows}")
        meta = {"method": method, "checkpoint": str(ck.manifest_path),
                "weights_sha256": ck.sha256, "steps": ck.steps, "trained_on": ck.train_on_label,
                "windows of": f"{source.train_on.label} (frame {opts.frame})"}
        out = reports_dir(reports) / "copilot4d"
        stem = f"{m.variant.name}-{ck.sha256[:12]}-on-{source.adapter.name}-{split}"
        if forecast:
            result = world_token_report(m, windows, max_windows=max_windows or None, log=lambda *_: None)
            sampled = f"{m.variant.name}-{ck.sha256[:12]}{_inference_suffix(m)}-on-{source.adapter.name}-{split}"
            md, csv_path = write_token_report(result, {**meta, "decoded": m.decoding(), "regenerate": regenerate}, out,
                                              f"world-tokens-{sampled}")
            for r in result["rows"]:
                sh = shares(r)
                click.echo(f"stride {r['stride']}, step {r['step']}: changed {sh['changed_share']:.1%}, accuracy on "
                           f"changed {sh['changed_accuracy']:.1%}, on unchanged {sh['unchanged_accuracy']:.1%}, "
                           f"moved {sh['moved_share']:.1%} (precision {sh['moved_precision']:.1%})")
            click.echo(f"wrote {md} and {csv_path}")
        if objective_draws:
            trained = open_training_data(train_on or ck.train_on["dataset"], ck.train_on["split"])
            if trained.adapter.fingerprint(ck.train_on["split"]).digest != ck.train_on["fingerprint"]:
                raise PcfbenchError(f"checkpoint {ck.manifest_path} was trained on {ck.train_on_label} of fingerprint "
                                    f"{ck.train_on['fingerprint']}; --train-on {train_on or ck.train_on['dataset']} "
                                    "has other data: name the data it trained on")
            if trained.train_on.key == source.train_on.key:
                raise PcfbenchError(f"--dataset {dataset_spec} --split {split} is the data {ck.manifest_path} trained "
                                    "on: the objective needs held-out windows (another split or dataset)")
            train_windows = windows_of(trained, ck.train_on["split"])
            if len(train_windows["tokens"]) != ck.manifest["config"].get("windows", len(train_windows["tokens"])):
                raise PcfbenchError(f"checkpoint {ck.manifest_path} trained on {ck.manifest['config']['windows']} "
                                    f"windows; {method} makes {len(train_windows['tokens'])} of "
                                    f"{ck.train_on_label}: its window options differ from its training's")
            sets = {f"trained on: {ck.train_on_label}": train_windows, f"held out: {source.train_on.label}": windows}
            res = objective_report(m.world, sets, n_past=cfg.n_past, variant=m.variant,
                                   label_smoothing=cfg.label_smoothing, draws=objective_draws,
                                   max_windows=max_windows or None, seed=int(opts.seed), log=lambda *_: None)
            went_on_from = ck.manifest["config"].get("init_from", {}).get("steps", 0)  # init_steps: its curve starts there
            md, csv_path = write_objective_report(
                res, {**meta, "regenerate": f"{regenerate} --objective-draws {objective_draws} --no-forecast"},
                out, f"world-objective-{stem}", curve=curve_tail(ck.dir / "curve.csv", first_step=went_on_from))
            for r in res["rows"]:
                sh = objective_shares(r)
                click.echo(f"{r['set']}, {r['objective']}: changed loss {sh['changed_loss']:.2f} "
                           f"(accuracy {sh['changed_accuracy']:.1%}), unchanged loss {sh['unchanged_loss']:.2f} "
                           f"(accuracy {sh['unchanged_accuracy']:.1%})")
            click.echo(f"wrote {md} and {csv_path}")


def _inference_suffix(method) -> str:
    """``-name=value`` for each inference option of ``method`` away from its default (sorted):
    what tells apart two reports of one checkpoint sampled differently."""
    defaults = type(method.options)()
    changed = sorted(f"{n}={getattr(method.options, n)}" for n in method.inference_options
                     if getattr(method.options, n) != getattr(defaults, n))
    return "".join(f"-{c}" for c in changed)


def _world_changes_command(cli):  # noqa: ANN001
    @cli.command("world-changes")
    @_world_options
    @click.option("--dataset", "dataset_spec", required=True, help="NAME or NAME=ROOT of the held-out samples")
    @click.option("--split", default="test", show_default=True)
    @click.option("--setting", required=True, help="The protocol setting whose samples are scored, e.g. kitti-1s")
    @click.option("--samples", "max_samples", type=int, default=12, show_default=True,
                  help="Evenly spaced samples (0: all).")
    @click.option("--shares", default=",".join(f"{p:g}" for p in (0.1, 0.25, 0.5)), show_default=True,
                  help="Comma-separated shares of the real changes the bound entries get right.")
    @click.option("--reports", default=None)
    def world_changes(method, train_on, train_split, checkpoint, dataset_spec, split, setting, max_samples, shares,
                      reports):
        """What a world model's changes are worth (frame t0): its forecast beside the t=0 map with only
        its right changes, with the real changes on a random share of the tokens, and the ceiling,
        with token-copy and copy-last, scored by the harness on the same samples (sees the future)."""
        from pcfbench.config import reports_dir
        from pcfbench.errors import PcfbenchError
        from pcfbench.methods.copilot4d.changes import (COLUMNS, COPY, FORECAST, HITS, check_shares, evaluate_changes,
                                                        write_changes)
        from pcfbench.methods.copilot4d.forecaster import Copilot4D

        try:
            values = check_shares(float(v) for v in shares.split(",") if v.strip())
        except ValueError:
            raise PcfbenchError(f"--shares {shares!r}: expected comma-separated numbers in (0, 1]") from None
        m, ck = _loaded(method, Copilot4D, "copilot4d or copilot4d-maskgit[:options]", train_on, train_split,
                        checkpoint)
        adapter = _open(dataset_spec)
        res = evaluate_changes(m, adapter, split, setting, change_shares=values, max_samples=max_samples or None,
                               log=click.echo)
        meta = {"method": method, "checkpoint": str(ck.manifest_path), "weights_sha256": ck.sha256,
                "steps": ck.steps, "trained_on": ck.train_on_label,
                "regenerate": f"pcfbench world-changes --method {method} --dataset {dataset_spec} --split {split} "
                              f"--setting {setting} --samples {max_samples} --shares {shares}"}
        md, csv_path = write_changes(res, meta, reports_dir(reports) / "copilot4d",
                                     f"world-changes-{m.variant.name}-{ck.sha256[:12]}{_inference_suffix(m)}-on-"
                                     f"{adapter.name}-{split}-"
                                     f"{setting}")
        ref = res["means"][COPY]
        for name in (FORECAST, HITS):
            click.echo(f"{name} / token-copy: " + ", ".join(f"{c} {res['means'][name][c] / ref[c]:.2f}"
                                                              for c in COLUMNS))
        click.echo(f"wrote {md} and {csv_path}")
