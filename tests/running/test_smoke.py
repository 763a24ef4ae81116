from click.testing import CliRunner

from pcfbench.cli import build_cli


def test_run_then_report_then_rerun_does_no_work(tiny_kitti, tmp_path):
    cli = build_cli()
    args = ["run", "--dataset", f"kitti={tiny_kitti}", "--setting", "kitti-1s", "--method", "copy-last",
            "--reports", str(tmp_path / "reports"), "-q"]
    first = CliRunner().invoke(cli, args)
    assert first.exit_code == 0, first.output
    assert "0 failed" in first.output
    for ext in ("md", "csv", "tex", "html"):
        assert (tmp_path / "reports" / f"leaderboard.{ext}").is_file()
    second = CliRunner().invoke(cli, args)
    assert second.exit_code == 0, second.output
    assert "nothing to do" in second.output
    md = (tmp_path / "reports" / "leaderboard.md").read_text()
    assert "copy-last" in md and "kitti / test / kitti-1s" in md


def test_a_limited_run_does_not_overwrite_a_complete_leaderboard(tiny_kitti, tmp_path):
    """A --limit run writes its report under reports/partial/: the complete leaderboard beside it
    keeps every byte, whether the limited run shares its store or starts a new one (a fresh clone's
    empty store beside the reports it ships)."""
    cli = build_cli()
    reports = tmp_path / "reports"
    base = ["run", "--dataset", f"kitti={tiny_kitti}", "--setting", "kitti-1s", "--method", "copy-last", "-q",
            "--reports", str(reports)]
    full = CliRunner().invoke(cli, base)
    assert full.exit_code == 0, full.output
    complete = {p.name: p.read_bytes() for p in reports.iterdir() if p.name.startswith("leaderboard")}
    assert "leaderboard.md" in complete and "partial" not in full.output
    for store in (reports / "store", tmp_path / "new-store"):
        res = CliRunner().invoke(cli, [*base, "--method", "raycast-zbuffer", "--limit", "2", "--store", str(store)])
        assert res.exit_code == 0, res.output
        assert {p.name: p.read_bytes() for p in reports.iterdir() if p.name.startswith("leaderboard")} == complete
        md = (reports / "partial" / "leaderboard.md").read_text()
        assert "PARTIAL" in md and "raycast-zbuffer" in md
        assert f"leaderboard: {reports / 'partial' / 'leaderboard.md'}\n" in res.output
        assert f"(a --limit run writes its report under {reports / 'partial'}; {reports / 'leaderboard.md'} is " \
               "written only by a run without --limit or by pcfbench report)" in res.output
