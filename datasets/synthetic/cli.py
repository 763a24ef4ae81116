"""``pcfbench generate``: write a synthetic domain in any layout that has a writer."""

from __future__ import annotations

from pathlib import Path

import click


def add_commands(cli: click.Group) -> None:
    from pcfbench.protocol import SAMPLE_POLICIES

    @cli.command()
    @click.argument("domain", default="synthetic-town")
    @click.option("--out", "-o", type=click.Path(file_okay=False), default=None,
                  help="Output folder; default: the cache the dataset reads (KITTI layout only).")
    @click.option("--layout", default="kitti", show_default=True,
                  help="kitti, or any layout of 'pcfbench convert' (nuscenes, av2, av2-sensor, mcap, ...).")
    @click.option("--split", "splits", multiple=True, help="Only these splits (repeatable); default: all.")
    @click.option("--quiet", "-q", is_flag=True, help="No progress bar.")
    def generate(domain, out, layout, splits, quiet):
        """Generate synthetic DOMAIN (synthetic-town, synthetic-suburb) deterministically."""
        from pcfbench.errors import PcfbenchError
        from pcfbench.datasets.synthetic.domains import get_domain
        from pcfbench.datasets.synthetic.generate import ensure_domain, generate_domain, get_writer

        dom = get_domain(domain)
        get_writer(layout)
        if out is None:
            if layout != "kitti":
                raise PcfbenchError(f"--layout {layout} needs --out DIR (the cache holds the KITTI layout the adapter reads)")
            click.echo(str(ensure_domain(dom, splits=tuple(splits) or None, progress=not quiet)))
            return
        manifest = generate_domain(dom, out, layout, progress=not quiet, splits=tuple(splits) or None)
        n = sum(s["sweeps"] for s in manifest["sequences"].values())
        click.echo(f"{dom.name}: {len(manifest['sequences'])} sequence(s), {n} sweeps in {manifest['seconds']:.1f} s -> {out} ({layout} layout)")

    @cli.group()
    def synthetic():
        """The generated world: compare it with real LiDAR."""

    @synthetic.command()
    @click.option("--real", required=True, metavar="NAME=ROOT",
                  help="The real dataset, e.g. kitti=/data/kitti-seq00 (root options ?key=value allowed).")
    @click.option("--domain", default="synthetic-town", show_default=True, metavar="NAME[=ROOT]",
                  help="The generated dataset (synthetic-town, synthetic-town-realistic, ...); default root: the cache.")
    @click.option("--out", "-o", type=click.Path(file_okay=False), required=True, help="Report folder (md, csv, json, png).")
    @click.option("--sweeps", type=click.IntRange(1), default=12, show_default=True,
                  help="Sweeps of each side (each with its successor, and the sweeps 0.5 s and 1 s later where there are) for the "
                       "statistics; the moving evidence reads every sweep 0.5 s apart.")
    @click.option("--setting", default="kitti-1s", show_default=True, help="Setting of the baselines' runs.")
    @click.option("--limit", type=click.IntRange(1), default=None,
                  help="Synthetic samples for the baselines, per split (default: all).")
    @click.option("--real-limit", type=click.IntRange(1), default=None,
                  help="Real samples for the baselines, per split (default: all).")
    @click.option("--policy", type=click.Choice(SAMPLE_POLICIES), default="full-context", show_default=True,
                  help="Sample policy of the synthetic baselines' cells.")
    @click.option("--real-policy", type=click.Choice(SAMPLE_POLICIES), default="full-context", show_default=True,
                  help="Sample policy of the real baselines' cells: subsample-500 or every-third spread the samples "
                       "over a long split (where --real-limit takes its first ones).")
    @click.option("--split", "synthetic_split", default=None, metavar="SPLIT[,SPLIT...]",
                  help="Synthetic split, or several pooled (train,val,test: every town; the report adds a table "
                       "per sequence). Default: the adapter's evaluation split.")
    @click.option("--real-split", default=None, metavar="SPLIT[,SPLIT...]",
                  help="Real split, or several pooled. Default: the adapter's evaluation split, else the first "
                       "with sequences.")
    @click.option("--store", type=click.Path(file_okay=False), default=None,
                  help="Results store for the baselines' cells (default: OUT/store; reused when run again).")
    @click.option("--no-baselines", is_flag=True, help="Statistics only (no method runs).")
    @click.option("--threads", type=click.IntRange(1), default=None, help="Thread budget of the baselines' runs.")
    @click.option("--quiet", "-q", is_flag=True, help="No progress bars.")
    def compare(real, domain, out, sweeps, setting, limit, real_limit, policy, real_policy, synthetic_split, real_split,
                store, no_baselines, threads, quiet):
        """Realism report: a generated domain beside a real dataset (ratios synthetic / real)."""
        from pcfbench.datasets.realism.compare import RANK_METRICS as RANK, pairs_phrase
        from pcfbench.datasets.realism.compare import compare as run_compare
        from pcfbench.plugins import get_setting

        get_setting(setting)
        res = run_compare(real, domain, out, sweeps=sweeps, setting=setting, limit=limit, real_limit=real_limit,
                          baselines=not no_baselines, store=store, real_split=real_split, synthetic_split=synthetic_split,
                          progress=not quiet, threads=threads, policy=policy, real_policy=real_policy)
        s, r = res["synthetic"], res["real"]
        for k in ("points per sweep", "static-scene residual median (m)", "roughness median (m)"):
            click.echo(f"{k}: synthetic {s[k]:.4g}, real {r[k]:.4g}, ratio {s[k] / r[k]:.3g}")
        click.echo(f"range histogram distance (TV): {res['range histogram distance (TV)']:.3f}")
        if "baselines" in res:
            trust = res["baselines"]["kendall_tau_bootstrap"]
            click.echo("kendall tau: " + ", ".join(
                f"{k} {t:+.2f}" + (f" (95 % interval {trust[k]['interval'][0]:+.2f} .. {trust[k]['interval'][1]:+.2f})"
                                   if k in trust else "")
                for k, t in res["baselines"]["kendall_tau"].items()))
            for side, agree in res["baselines"]["between_sequences"].items():
                if agree:
                    click.echo(f"{side} sequences against each other (mean kendall tau over "
                               f"{pairs_phrase(agree[RANK[0]]['pairs'])}): " + ", ".join(f"{k} {a['mean']:+.2f}" for k, a in agree.items()))
        click.echo(f"report: {Path(out) / 'realism.md'}")
