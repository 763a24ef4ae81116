"""The kernel warm-up of a run that generates data (pcfbench.running.warmup)."""

from __future__ import annotations

import os

from pcfbench.running.warmup import KernelWarmup, preparing_data, warm, warm_while_preparing


def test_warm_forecasts_and_scores_each_untrained_method_and_skips_the_rest():
    # every registered method that needs no checkpoint, none of the trained ones
    assert warm(None, ("chamfer_nf", "l1_median")) == [
        "copy-last", "raycast-4docc", "raycast-freespace", "raycast-voxel", "raycast-zbuffer"]
    # options as on the command line; a trained method, an unknown one and a bad option are
    # left to the cells, which report them
    assert warm(("raycast-voxel:voxel=0.4", "copilot4d-token-copy", "no-such-method", "copy-last:nope=1"),
                ("chamfer_nf",)) == ["raycast-voxel"]
    assert warm(("copy-last",), ("no-such-metric",)) == []


def test_the_warm_up_starts_only_when_data_is_prepared_and_is_waited_for():
    preparing_data()  # no run registered one: nothing happens
    with warm_while_preparing(("copy-last",), ("chamfer_nf",)) as idle:
        pass
    assert idle.process is None  # nothing generated, no process
    with warm_while_preparing(("copy-last",), ("chamfer_nf",)) as w:
        preparing_data()
        first = w.process
        preparing_data()  # a second split: the same warm-up
        assert first is not None and w.process is first
    assert first.returncode == 0  # the block waited for it
    preparing_data()  # outside the block again: nothing
    assert w.process is first


def test_a_failed_preparation_ends_the_warm_up_instead_of_waiting_for_it():
    import pytest

    with pytest.raises(KeyboardInterrupt):
        with warm_while_preparing(None, ("chamfer_nf",)) as w:
            preparing_data()
            raise KeyboardInterrupt  # as Ctrl-C during the generation
    assert w.process.returncode is not None and w.process.returncode < 0  # killed, not finished
    preparing_data()  # and no longer registered


def test_the_warm_up_fills_the_numba_cache_the_workers_read(tmp_path, monkeypatch):
    # numba writes its cache under NUMBA_CACHE_DIR when set; the child process inherits it
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path))
    w = KernelWarmup(("copy-last",), ("chamfer_nf",))
    w.start()
    w.join()
    assert w.process.returncode == 0
    indexes = [p for p in tmp_path.rglob("*.nbi")]
    # the metric's nearest-neighbour kernels (bench/metrics/nn.py), compiled and saved
    assert any(p.name.startswith("nn.") for p in indexes), sorted(os.path.relpath(p, tmp_path) for p in indexes)


def test_two_warm_ups_share_the_methods_by_claims(tmp_path):
    """Each method is warmed by the one warm-up that claims it first: the second finds the
    first's claims and warms none of them; one from the end stops where the other began."""
    methods = ("copy-last", "raycast-zbuffer", "raycast-4docc")
    (tmp_path / "a").mkdir()
    assert warm(methods, ("chamfer_nf",), str(tmp_path / "a"), reverse=True) == [
        "raycast-4docc", "raycast-zbuffer", "copy-last"]
    (tmp_path / "b").mkdir()
    (tmp_path / "b" / "1.claim").touch()  # raycast-zbuffer taken by another
    assert warm(methods, ("chamfer_nf",), str(tmp_path / "b")) == ["copy-last", "raycast-4docc"]
    assert warm(methods, ("chamfer_nf",), str(tmp_path / "b"), reverse=True) == []


def test_once_the_data_is_ready_a_second_warm_up_helps_the_first():
    w = KernelWarmup(("copy-last", "raycast-zbuffer"), ("chamfer_nf",))
    w.start()
    claims = w._claims.name
    w.join()  # the first child is still importing: a helper starts, from the end
    assert w.helper is not None and w.process.returncode == 0 and w.helper.returncode == 0
    assert not os.path.exists(claims)  # the shared folder is gone with them
