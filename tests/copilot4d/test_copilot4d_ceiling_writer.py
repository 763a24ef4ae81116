"""The one ceiling writer every world model uses (copilot4d, occworld, bevworld)."""

from __future__ import annotations

import csv

from pcfbench.methods.copilot4d.ceiling import write_beside


def test_writer_gives_ratios_and_the_bar_per_column(tmp_path):
    means = {"ceiling": {"chamfer_nf": 1.0, "l1_mean": 3.0, "l1_median": 0.5, "broken": float("nan")},
             "occ-copy": {"chamfer_nf": 2.0, "l1_mean": 2.0, "l1_median": 0.5, "broken": 1.0},
             "copy-last": {"chamfer_nf": 4.0, "l1_mean": 6.0, "l1_median": 1.0, "broken": 1.0}}
    result = {"means": means, "dataset": "d", "split": "test", "setting": "kitti-1s", "frame": "own",
              "readout": "expected", "samples": 3, "sweeps": 15}
    md, csv_path = write_beside(result, {"config": "tiny"}, tmp_path, "c", copy="occ-copy", target="x's target",
                                head=["# title", ""], issue=7, columns=("readout",))
    rows = list(csv.DictReader(open(csv_path)))
    assert [r["entry"] for r in rows][1:] == ["occ-copy", "copy-last", "ratio ceiling / occ-copy",
                                             "ratio ceiling / copy-last"]
    assert "broken" not in rows[0]  # a column any entry could not score is left out, not averaged
    assert rows[0]["readout"] == "expected" and rows[0]["samples"] == "3"
    assert [float(rows[3][k]) for k in ("chamfer_nf", "l1_mean", "l1_median")] == [0.5, 1.5, 1.0]
    assert [float(rows[4][k]) for k in ("chamfer_nf", "l1_mean", "l1_median")] == [0.25, 0.5, 0.5]
    text = md.read_text()
    # a tie is not a win
    assert "issue 7: the ceiling beats occ-copy" in text
    assert "chamfer_nf met, l1_mean NOT met, l1_median NOT met." in text
    assert text.startswith("# title\n") and "- config: tiny" in text


def test_a_ceiling_of_some_samples_is_written_beside_the_whole_splits(tmp_path):
    means = {n: {"chamfer_nf": 1.0, "l1_mean": 1.0, "l1_median": 1.0} for n in ("ceiling", "occ-copy", "copy-last")}
    result = {"means": means, "dataset": "d", "split": "test", "setting": "kitti-1s", "frame": "t0", "sweeps": 15}
    whole = write_beside({**result, "samples": 84, "of_samples": 84}, {}, tmp_path, "c", copy="occ-copy", target="x",
                         head=[], issue=7)
    some = write_beside({**result, "samples": 12, "of_samples": 84}, {}, tmp_path, "c", copy="occ-copy", target="x",
                        head=[], issue=7)
    assert [p.name for p in whole] == ["c.md", "c.csv"]
    assert [p.name for p in some] == ["c-12-samples.md", "c-12-samples.csv"]
    assert list(csv.DictReader(open(whole[1])))[0]["samples"] == "84"  # left as it was
