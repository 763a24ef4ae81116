"""How many of physics 10's yard trees stand inside a building (docs/realism.md, "Physics 10"):
the static worlds of towns 05, 06 and 00; a trunk inside a STRUCTURE box's footprint, and of
those the crowns that rise above that box.

    .venv/bin/python docs/experiments/realism_yard_trees_inside.py
"""

from __future__ import annotations

import dataclasses

from matplotlib.path import Path as Polygon

from pcfbench.datasets.synthetic import generate as G
from pcfbench.datasets.synthetic import realism as R
from pcfbench.datasets.synthetic.domains import get_domain
from pcfbench.datasets.synthetic.world import STRUCTURE, TRUNK, VEGETATION

seen = {}
plant = R.add_yard_trees


def spy(soup, *args):
    trunks, crowns = len(soup.parts.get(TRUNK, [])), len(soup.parts.get(VEGETATION, []))
    plant(soup, *args)
    seen.update(trees=list(zip(soup.parts[TRUNK][trunks:], soup.parts[VEGETATION][crowns:])),
                boxes=[v for v, _ in soup.parts[STRUCTURE] if len(v) == 8])


R.add_yard_trees = spy
total = inside = above = 0
for seq in ("05", "06", "00"):
    G.simulate_sequence(dataclasses.replace(get_domain("synthetic-town-realistic"), splits={"test": ((seq, 1),)}), seq)
    # a box's bottom corners in either winding (a wrong one gives a bow tie, a subset of the box)
    boxes = [(Polygon(v[idx, :2]), v[:, 2].max()) for v in seen["boxes"] for idx in ([0, 1, 2, 3], [0, 1, 3, 2])]
    for (trunk, _), (crown, _) in seen["trees"]:
        roofs = [top for poly, top in boxes if poly.contains_point(trunk[:, :2].mean(0))]
        total += 1
        inside += bool(roofs)
        above += bool(roofs) and crown[:, 2].max() > max(roofs)
print(f"yard trees {total}: trunk inside a building's footprint {inside} ({inside / total:.0%}); "
      f"of those, crown above the roof {above}")
