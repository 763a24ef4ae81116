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
