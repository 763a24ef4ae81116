"""Published results as reference rows: in a block of their own under the paper preset's
groups of the papers' dataset, split and setting, never ranked, never in an interval."""

from __future__ import annotations

import pytest

from pcfbench.errors import PcfbenchError
from pcfbench.method import resolve_method
from pcfbench.reporting import tables
from pcfbench.reporting.published import load_published, parse_published, reported_for
from pcfbench.reporting.report import collect
from pcfbench.running.runner import RunOptions, run_cell
from pcfbench.store.cells import CellSpec


def test_the_shipped_rows_are_copilot4ds_tables_as_printed():
    rows = load_published()
    assert len(rows) == 12 and {r.method for r in rows} == {"4D-Occ", "Copilot4D"}
    kitti = {r.method: dict(r.values) for r in reported_for("kitti", "test", "kitti-1s", "full-context", rows)}
    assert kitti == {
        "4D-Occ": {"chamfer_nf": "0.51", "l1_median": "0.20", "absrel_median": "2.52", "l1_mean": "1.12",
                   "absrel_mean": "9.09", "chamfer": "0.61"},
        "Copilot4D": {"chamfer_nf": "0.18", "l1_median": "0.11", "absrel_median": "1.32", "l1_mean": "0.95",
                      "absrel_mean": "8.59", "chamfer": "0.21"},
    }
    nus3 = reported_for("nuscenes", "val", "nuscenes-3s", "full-context", rows)
    assert [r.values["chamfer"] for r in nus3] == ["4.31", "2.47"]
    # only where the dataset, split and setting are the papers' (and the policy, where stated)
    assert not reported_for("kitti", "val", "kitti-1s", "full-context", rows)
    assert not reported_for("nuscenes", "val", "kitti-1s", "full-context", rows)
    assert not reported_for("synthetic-town-realistic", "test", "kitti-1s", "every-third", rows)
    assert not reported_for("av2", "val", "av2-1s", "full-context", rows)  # Table 2: 4,000 subsampled frames
    av2 = reported_for("av2", "val", "av2-3s", "subsample-4000", rows)
    assert [(r.method, r.values["l1_mean"], "chamfer" in r.values) for r in av2] == [("4D-Occ", "2.62", False),
                                                                                      ("Copilot4D", "1.99", False)]


@pytest.mark.parametrize("text, match", [
    ('[[reported]]\nmethod = "x"\n', r"reported row 1 must have the keys"),
    ('[[reported]]\nmethod = "x"\nsource = "s"\ndataset = "d"\nsplit = "t"\nsetting = "k"\nvalues = { a = 1.0 }\n',
     r"values must map metrics to the printed numbers as strings"),
    ('[[reported]]\nmethod = "x"\nsource = "s"\ndataset = "d"\nsplit = "t"\nsetting = "k"\nvalues = { a = "n/a" }\n',
     r"value 'n/a' is not a number"),
    ('[other]\n', r"expected only \[\[reported\]\] tables"),
])
def test_a_bad_published_file_is_one_error(text, match):
    with pytest.raises(PcfbenchError, match=match):
        parse_published(text, "pub.toml")


def test_the_paper_preset_shows_them_apart_and_ranks_only_the_store(tiny_kitti, store):
    spec = CellSpec("copy-last", {}, resolve_method("copy-last").options_hash, "kitti", str(tiny_kitti), "test",
                    "kitti-1s", "full-context", None, ("chamfer_nf", "chamfer"))
    run_cell(spec, store, RunOptions(progress=False))
    lb = collect(store)
    presets = tables.load_presets()
    assert presets["paper"].reported and presets["roi"].reported and not presets["full"].reported
    t = tables.build(lb, presets["paper"])
    (group,) = t.groups
    assert [r.method for r in group.reported] == ["4D-Occ", "Copilot4D"] and list(group.rows["variant"]) == ["copy-last"]
    md = tables.markdown(t)
    block = md.split(tables.REPORTED_TITLE)[1]
    assert "| 4D-Occ | Copilot4D (Zhang et al., ICLR 2024), Table 1 | 0.51 | 0.61 |" in block
    assert "| Copilot4D | Copilot4D (Zhang et al., ICLR 2024), Table 1 | 0.18 | 0.21 |" in block
    assert md.index("| copy-last (ref) |") < md.index(tables.REPORTED_TITLE)
    assert group.best == {"chamfer_nf": float(group.rows["chamfer_nf"].iloc[0]), "chamfer": float(group.rows["chamfer"].iloc[0])}
    assert "0.18" in tables.html_page(t) and "Copilot4D (reported: Copilot4D" in tables.text(t)
    # a preset without reported = true, and a group of another split: no block
    assert tables.REPORTED_TITLE not in tables.markdown(tables.build(lb, presets["full"]))
    lb.table["split"] = "val"
    other = tables.build(lb, presets["paper"])
    assert not other.groups[0].reported and tables.REPORTED_TITLE not in tables.markdown(other)
