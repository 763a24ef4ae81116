"""Published results and a user's results never share files: runs write to ./reports by
default, which the checkout does not track; the published results live in docs/results/."""

from __future__ import annotations

import subprocess
from pathlib import Path

from click.testing import CliRunner

from pcfbench import config
from pcfbench.cli import build_cli

REPO = Path(__file__).resolve().parents[2]


def _git(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(["git", "-C", str(REPO), *args], capture_output=True, text=True)


def _ignored(path: str) -> bool:
    """Whether the checkout's .gitignore ignores ``path`` (tracked or not, present or not)."""
    res = _git("check-ignore", "--no-index", "-q", path)
    assert res.returncode in (0, 1), res.stderr
    return res.returncode == 0


def test_the_default_reports_folder_is_no_published_file(tiny_kitti, tmp_path, monkeypatch):
    # what a run writes without --reports: ./reports, its store ./reports/store, a partial run ./reports/partial
    work = tmp_path / "work"
    work.mkdir()
    monkeypatch.chdir(work)
    assert config.reports_dir() == Path("reports") and config.store_dir() == Path("reports/store")
    assert config.partial_reports_dir(config.reports_dir()) == Path("reports/partial")
    res = CliRunner().invoke(build_cli(), ["run", "-d", f"kitti={tiny_kitti}", "-s", "kitti-1s", "-m", "copy-last", "-q"])
    assert res.exit_code == 0, res.output
    written = sorted(str(p.relative_to(work)) for p in work.rglob("*") if p.is_file())
    assert written and all(w.startswith("reports/") for w in written)

    # in the checkout, only the folder's README is tracked there (a run never writes it) and
    # everything a run writes there is ignored
    tracked = _git("ls-files", "--", "reports")
    assert tracked.returncode == 0 and tracked.stdout == "reports/README.md\n", tracked.stdout + tracked.stderr
    assert "reports/README.md" not in written and not _ignored("reports/README.md")
    for w in [*written, "reports/partial/leaderboard.md", "reports/sweeps/raycast-voxel-size.md"]:
        assert _ignored(w), f"{w} would show in git status after a default run"
    # the published results: tracked in docs/results/; the store that regenerates them and a
    # partial run there (--reports docs/results --limit N) ignored
    published = _git("ls-files", "--", "docs/results/leaderboard.md", "docs/results/sweeps/raycast-voxel-size.md")
    assert published.stdout.split() == ["docs/results/leaderboard.md", "docs/results/sweeps/raycast-voxel-size.md"]
    assert not _ignored("docs/results/leaderboard.md")
    assert _ignored("docs/results/store/cell.json") and _ignored("docs/results/partial/leaderboard.md")
