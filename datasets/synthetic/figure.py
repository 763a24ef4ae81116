"""Bird's-eye views of generated sweeps: ``python -m pcfbench.datasets.synthetic.figure [OUT.png]``.

Top row: one sweep of each domain coloured by semantic class, with the ego trajectory.
Bottom row: three sweeps of the same sequence 1 s apart (colour = time) around the ego
vehicle, in the world frame: static structure overlaps, moving agents leave trails.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from pcfbench.geometry import transform_points
from pcfbench.datasets.synthetic.domains import get_domain
from pcfbench.datasets.synthetic.generate import simulate_sequence
from pcfbench.datasets.synthetic.world import CLASS_NAMES

COLOURS = ["#b0b0b0", "#4c72b0", "#000000", "#55a868", "#8172b2", "#c44e52", "#dd8452", "#e377c2", "#7f7f7f", "#8c564b"]


def render(out: Path, town_seq: str = "05", suburb_seq: str = "05") -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 2, figsize=(13, 13))
    for col, (name, seq_name, span, picks) in enumerate(
        (("synthetic-town", town_seq, 75.0, (0, 10, 20)), ("synthetic-suburb", suburb_seq, 60.0, (0, 2, 4)))
    ):
        dom = get_domain(name)
        n = max(picks) + 1
        seq = simulate_sequence(dom, seq_name)
        T = seq.T_world_sensor
        # top: one sweep by class
        ax = axes[0, col]
        pts = transform_points(T[0], seq.points[0])
        cls = seq.labels[0] & 0xFFFF
        for c in np.unique(cls):
            m = cls == c
            ax.scatter(pts[m, 0], pts[m, 1], s=0.15, c=COLOURS[int(c)], label=CLASS_NAMES[int(c)], rasterized=True)
        ax.plot(T[:, 0, 3], T[:, 1, 3], "r-", lw=2, label="ego path")
        o = T[0, :2, 3]
        ax.set_xlim(o[0] - span, o[0] + span)
        ax.set_ylim(o[1] - span, o[1] + span)
        ax.set_aspect("equal")
        ax.set_title(f"{name} seq {seq_name}: sweep 0 ({len(pts):,} points, {dom.sensor.beams} beams)")
        ax.legend(loc="upper right", markerscale=20, fontsize=7)
        # bottom: sweeps over time near the ego vehicle, moving agents highlighted
        ax = axes[1, col]
        cmap = plt.get_cmap("viridis")
        for j, k in enumerate(picks):
            p = transform_points(T[k], seq.points[k])
            c = seq.labels[k] & 0xFFFF
            moving = (c >= 5) & (c <= 7)
            ax.scatter(p[~moving, 0], p[~moving, 1], s=0.1, color="#c8c8c8", rasterized=True)
            ax.scatter(p[moving, 0], p[moving, 1], s=1.5, color=cmap(j / max(len(picks) - 1, 1)),
                       label=f"agents at t = {seq.times_s[k]:.1f} s", rasterized=True)
        ax.plot(T[: n, 0, 3], T[: n, 1, 3], "r-", lw=2)
        c0 = T[picks[len(picks) // 2], :2, 3]
        ax.set_xlim(c0[0] - 35, c0[0] + 35)
        ax.set_ylim(c0[1] - 35, c0[1] + 35)
        ax.set_aspect("equal")
        ax.set_title(f"{name}: moving agents over {seq.times_s[picks[-1]]:.0f} s (grey: static, world frame)")
        ax.legend(loc="upper right", markerscale=6, fontsize=8)
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=90)
    plt.close(fig)
    return out


def main(argv: list[str] | None = None) -> None:
    argv = sys.argv[1:] if argv is None else argv
    out = Path(argv[0]) if argv else Path("reports/synthetic_bev.png")
    print(render(out))


if __name__ == "__main__":
    main()
