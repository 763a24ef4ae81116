"""What each world-physics feature costs to generate (docs/realism.md, "What each feature costs").

Simulates test sequence 05 of ``synthetic-town-realistic`` (60 sweeps, nothing written) once
per variant: physics 1, physics 4, and physics 4 with one feature changed; the variants
alternate, ROUNDS times (default 3), one thread. Prints each run, then a table of medians
(seconds, points per sweep, ratios to physics 1 and physics 4); writes OUT (default
realism-generation-cost.json) with every run's time.

    OMP_NUM_THREADS=1 .venv/bin/python docs/experiments/realism_generation_cost.py [ROUNDS] [OUT]

Without rough surfaces, ``realism.surface_displacement`` is swapped for zeros (no value noise,
no verge test). Run it on an otherwise idle machine: a neighbour's job moves these times.
"""

from __future__ import annotations

import dataclasses
import json
import statistics
import sys
import time

import numpy as np

from pcfbench.datasets.synthetic import generate, realism
from pcfbench.datasets.synthetic.domains import DOMAINS


def main(rounds: int = 3, out: str = "realism-generation-cost.json") -> None:
    town, real = DOMAINS["synthetic-town"], DOMAINS["synthetic-town-realistic"]
    knobs = real.realism
    rough = realism.surface_displacement

    def changed(**kw):
        return dataclasses.replace(real, realism=dataclasses.replace(knobs, **kw))

    variants = {  # name: (domain, smooth surfaces)
        "physics 1 (512 columns)": (town, False),
        "physics 4 (2048 columns)": (real, False),
        "physics 4 at 512 columns": (dataclasses.replace(real, sensor=town.sensor), False),
        "physics 4 without rough surfaces": (real, True),
        "physics 4 without shrubs": (changed(shrubs_per_100m=(0.0, 0.0)), False),
        "physics 4 without mixed pixels": (changed(mixed_prob=0.0), False),
        "physics 4 with motion distortion": (changed(motion_distortion=True), False),
    }
    times: dict[str, list[float]] = {k: [] for k in variants}
    points: dict[str, float] = {}
    try:
        for r in range(rounds):
            for name, (domain, smooth) in variants.items():
                realism.surface_displacement = (lambda p, c, k, g=None: np.zeros(len(p))) if smooth else rough
                t0 = time.perf_counter()
                seq = generate.simulate_sequence(domain, "05")
                times[name].append(time.perf_counter() - t0)
                points[name] = seq.stats["mean_points"]
                print(r, name, f"{times[name][-1]:.1f} s", f"{points[name]:.0f} points", flush=True)
    finally:
        realism.surface_displacement = rough
    p1, p4 = (statistics.median(times[k]) for k in ("physics 1 (512 columns)", "physics 4 (2048 columns)"))
    result = {k: {"median_s": statistics.median(t), "runs_s": t, "points": points[k],
                  "x_physics1": statistics.median(t) / p1, "x_physics4": statistics.median(t) / p4}
              for k, t in times.items()}
    with open(out, "w") as f:
        json.dump(result, f, indent=1)
    print("| sequence 05, 60 sweeps | seconds | points per sweep | x physics 1 | x physics 4 |")
    for k, o in result.items():
        print(f"| {k} | {o['median_s']:.1f} | {o['points']:,.0f} | {o['x_physics1']:.2f} | {o['x_physics4']:.2f} |")


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 3, sys.argv[2] if len(sys.argv) > 2 else "realism-generation-cost.json")
