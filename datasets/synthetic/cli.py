"""``pcfbench generate``: write a synthetic domain in any layout that has a writer."""

from __future__ import annotations

import click


def add_commands(cli: click.Group) -> None:
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
