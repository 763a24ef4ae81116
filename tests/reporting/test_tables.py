"""Table rows a page can hold: a trained method's training data and checkpoint go to a
footnote, and the preset titles say what the table shows."""

from __future__ import annotations

import numpy as np
import pandas as pd

from pcfbench.reporting import htmlreport, tables
from pcfbench.reporting.report import Leaderboard

LONG = "copilot4d-token-copy [trained on synthetic-town-realistic:train, ck 84120cdf]"
OTHER_CK = "copilot4d-token-copy [trained on synthetic-town-realistic:train, ck 0badc0de]"
OWN = "copilot4d-token-copy [trained on kitti:test, ck 11111111, ON ITS TRAINING DATA]"


def _lb(variants: list[str]) -> Leaderboard:
    n = len(variants)
    table = pd.DataFrame({
        "dataset": "synthetic-town", "split": "test", "setting": "kitti-1s", "policy": "full-context",
        "limit": None, "horizon_s": 1.0, "variant": variants, "method": [v.split(" ")[0] for v in variants],
        "samples": 4, "sweeps": 20, "failed": 0, "is_reference": [v == "copy-last" for v in variants],
        "cell_dir": [f"/store/cell{i}" for i in range(n)],
        "l1_mean": np.linspace(0.5, 0.9, n), "l1_mean_lo": 0.4, "l1_mean_hi": 1.0,
        "l1_mean_rel": 0.0, "l1_mean_p": 1.0,
    })
    return Leaderboard(table=table, by_step=pd.DataFrame(), metric_columns=["l1_mean"], units={"l1_mean": "m"},
                       higher_is_better={"l1_mean": False})


def _table(variants):
    preset = tables.Preset("t", "a table", (tables.Column("l1_mean", "L1 Mean"),), "l1_mean")
    return tables.build(_lb(variants), preset)


def test_a_trained_row_is_its_method_name_and_a_marker_with_the_training_data_in_a_footnote():
    t = _table(["copy-last", LONG, OTHER_CK, OWN])
    labels = [tables._label(r, t.groups[0]) for _, r in t.groups[0].rows.iterrows()]
    assert labels == ["copy-last (ref)", "copilot4d-token-copy¹", "copilot4d-token-copy²",
                      "copilot4d-token-copy³ (ON ITS TRAINING DATA)"]
    tc = "copilot4d-token-copy trained on"
    assert tables.footnote_lines(t) == [f"¹ {tc} synthetic-town-realistic:train, checkpoint sha256 84120cdf",
                                        f"² {tc} synthetic-town-realistic:train, checkpoint sha256 0badc0de",
                                        f"³ {tc} kitti:test, checkpoint sha256 11111111"]
    md = tables.markdown(t)
    assert "| copilot4d-token-copy¹ |" in md and f"¹ {tc} synthetic-town-realistic:train, checkpoint sha256 84120cdf" in md
    assert LONG not in md and LONG not in tables.text(t) and f"¹ {tc}" in tables.text(t)
    tex, _fit = tables.latex(t)
    assert r"copilot4d-token-copy$^1$ &" in tex and rf"$^1$ {tc} synthetic-town-realistic:train, checkpoint sha256 84120cdf" in tex
    assert _fit.startswith("fits the A4 text width (455 pt) in \\small")  # the 75-character label made it \footnotesize
    for page in (tables.html_page(t), htmlreport.page(t, _lb(["copy-last"]))):
        assert "copilot4d-token-copy¹" in page and "sha256 84120cdf" in page and LONG not in page


def test_one_checkpoint_on_two_rows_shares_one_footnote_and_plain_rows_have_none():
    short, notes = tables.footnote_labels([LONG, "raycast-voxel (voxel=0.4)", LONG])
    assert short == {LONG: "copilot4d-token-copy¹"} and len(notes) == 1
    assert tables.footnote_labels(["copy-last", "raycast-voxel (voxel=0.4)"]) == ({}, [])


def test_the_shipped_presets_titles_say_what_the_table_is_not_whose_layout_it_borrows():
    for preset in tables.load_presets().values():
        assert "Copilot4D" not in preset.title, preset.title


def test_the_transfer_table_arrows_follow_each_metric_s_direction():
    import pandas as pd

    from pcfbench.reporting.transfer import markdown

    rows = pd.DataFrame([{
        "dataset": "kitti", "split": "test", "setting": "kitti-1s", "policy": "full-context", "limit": float("nan"),
        "horizon_s": 1.0, "method_label": "m", "train_on": "town:train", "checkpoint_sha256": "ab" * 32,
        "on_training_data": False, "samples": 3, "chamfer_nf": 0.5, "l1_mean": 0.25,
    }])
    text = markdown(rows, {"chamfer_nf": "m^2", "l1_mean": "m"}, higher_is_better={"l1_mean": True})
    head = next(line for line in text.splitlines() if line.startswith("| Method"))
    assert "Chamfer ↓" in head and "L1 Mean ↑" in head and "L1 Mean ↓" not in head
    # no directions given: every column is lower-is-better, as before
    assert "L1 Mean ↓" in markdown(rows, {"chamfer_nf": "m^2", "l1_mean": "m"})


def test_a_transfer_block_whose_rows_scored_different_samples_says_so():
    import pandas as pd

    from pcfbench.reporting.transfer import markdown

    row = {"dataset": "kitti", "split": "test", "setting": "kitti-1s", "policy": "full-context", "limit": float("nan"),
           "horizon_s": 1.0, "method_label": "copy-last", "train_on": "", "checkpoint_sha256": "",
           "on_training_data": False, "samples": 28, "chamfer_nf": 0.5}
    same = pd.DataFrame([row, dict(row, method_label="m", train_on="town:train", checkpoint_sha256="ab" * 32)])
    assert "scored a subset" not in markdown(same, {"chamfer_nf": "m^2"})
    text = markdown(same.assign(samples=[28, 8]), {"chamfer_nf": "m^2"})
    assert "Rows with n below 28 scored a subset of the samples" in text
