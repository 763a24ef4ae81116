"""How many of physics 10's yard trees stand inside a building (docs/realism.md, "Where it is
still unlike the real drive"): the static worlds of towns 05, 06 and 00 (by default); a trunk
inside a STRUCTURE box's footprint, and of those the crowns that rise above that box.

    .venv/bin/python docs/experiments/realism_yard_trees_inside.py [--sequences 05,06,00]

Each town's static world is built and one sweep simulated (a few seconds a town).
"""

from __future__ import annotations

import argparse
import dataclasses

from matplotlib.path import Path as Polygon

from pcfbench.datasets.synthetic import generate as G
from pcfbench.datasets.synthetic import realism as R
from pcfbench.datasets.synthetic.domains import get_domain
from pcfbench.datasets.synthetic.world import STRUCTURE, TRUNK, VEGETATION


def count(sequences: list[str]) -> tuple[int, int, int]:
    """(yard trees, trunks inside a building's footprint, of those crowns above its roof) over
    the static worlds of ``sequences``."""
    seen = {}
    plant = R.add_yard_trees

    def spy(soup, *args):
        trunks, crowns = len(soup.parts.get(TRUNK, [])), len(soup.parts.get(VEGETATION, []))
        plant(soup, *args)
        seen.update(trees=list(zip(soup.parts[TRUNK][trunks:], soup.parts[VEGETATION][crowns:])),
                    boxes=[v for v, _ in soup.parts[STRUCTURE] if len(v) == 8])

    total = inside = above = 0
    R.add_yard_trees = spy
    try:
        for seq in sequences:
            seen.clear()
            G.simulate_sequence(dataclasses.replace(get_domain("synthetic-town-realistic"), splits={"test": ((seq, 1),)}), seq)
            # a box's bottom corners in either winding (a wrong one gives a bow tie, a subset of the box)
            boxes = [(Polygon(v[idx, :2]), v[:, 2].max()) for v in seen["boxes"] for idx in ([0, 1, 2, 3], [0, 1, 3, 2])]
            for (trunk, _), (crown, _) in seen["trees"]:
                roofs = [top for poly, top in boxes if poly.contains_point(trunk[:, :2].mean(0))]
                total += 1
                inside += bool(roofs)
                above += bool(roofs) and crown[:, 2].max() > max(roofs)
    finally:
        R.add_yard_trees = plant
    return total, inside, above


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sequences", default="05,06,00", help="towns, comma-separated")
    total, inside, above = count(ap.parse_args().sequences.split(","))
    print(f"yard trees {total}: trunk inside a building's footprint {inside} ({inside / max(total, 1):.0%}); "
          f"of those, crown above the roof {above}")


if __name__ == "__main__":
    main()
