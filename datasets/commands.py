"""``pcfbench export`` and ``pcfbench convert`` (added through the register_commands hook)."""

from __future__ import annotations

from pathlib import Path

import click

from pcfbench.errors import PcfbenchError
from pcfbench.datasets.layout import STANDARD_AXES, SequenceData, change_axes

#: convert targets: layout name -> (axis convention, description)
LAYOUTS = {
    "kitti": (STANDARD_AXES, "KITTI Odometry (sequences/NN/velodyne, calib.txt, times.txt, poses/NN.txt)"),
    "nuscenes": ("x right, y forward, z up", "nuScenes v1.0-trainval tables + samples/LIDAR_TOP"),
    "av2": (STANDARD_AXES, "Argoverse 2 LiDAR dataset layout"),
    "av2-sensor": (STANDARD_AXES, "Argoverse 2 Sensor dataset layout"),
    "mcap": (STANDARD_AXES, "ROS 2 MCAP recordings (PointCloud2 + /tf), one per sequence"),
    "mcap-foxglove": (STANDARD_AXES, "Foxglove MCAP recordings (protobuf foxglove.PointCloud + FrameTransform)"),
    "mcap-json": (STANDARD_AXES, "Foxglove MCAP recordings (JSON foxglove.PointCloud + FrameTransform)"),
}


def open_adapter(spec: str):
    """``NAME[=ROOT]`` (ROOT may carry ``?key=value`` options) into an adapter instance; without
    a ROOT the configured one (environment, config file) or the embedded default is used."""
    from pcfbench import config
    from pcfbench.plugins import get_plugins

    (name,), roots = config.parse_dataset_args((spec,))
    cls = get_plugins().datasets.get(name)
    return config.open_adapter(name, cls, config.resolve_root(name, cls, roots))


def source_sequences(adapter, splits: tuple[str, ...]) -> list[SequenceData]:
    out = []
    for split in splits or adapter.splits():
        for name in adapter.sequence_names(split):
            seq = adapter.sequence(name)
            out.append(SequenceData(name, split, seq.T_world_sensor, seq.timestamps_ns, seq.load_points))
    return out


def _rename(seqs: list[SequenceData], pools: dict[str, list[str]], default_split: str, layout: str) -> list[SequenceData]:
    """Give each sequence a name the target's split lists know (kept when it already is one)."""
    used, out = set(), []
    for s in seqs:
        split = s.split if s.split in pools else default_split
        pool = pools[split]
        name = s.name if s.name in pool and s.name not in used else next((n for n in pool if n not in used), None)
        if name is None:
            raise PcfbenchError(f"{layout}: split {split} holds only {len(pool)} sequences; cannot place {s.name}")
        used.add(name)
        out.append(SequenceData(name, split, s.T_world_sensor, s.timestamps_ns, s.load))
    return out


def write_layout(layout: str, out: Path, seqs: list[SequenceData]) -> list[tuple[str, str]]:
    """Write ``seqs`` in ``layout`` under ``out``; returns (source name, written name) pairs."""
    if layout == "kitti":
        from pcfbench.datasets.kitti import SPLITS, write_kitti_sequence

        named = _rename(seqs, {k: list(v) for k, v in SPLITS.items()}, "test", layout)
        for s in named:
            times = (s.timestamps_ns - s.timestamps_ns[0]) / 1e9
            write_kitti_sequence(out, s.name, (s.load(i) for i in range(len(s))), s.T_world_sensor, times)
    elif layout == "nuscenes":
        from pcfbench.datasets.nuscenes import official_splits, write_nuscenes

        sp = official_splits()
        named = _rename(seqs, {"train": sp["train"], "val": sp["val"]}, "val", layout)
        write_nuscenes(out, named)
    elif layout in ("av2", "av2-sensor"):
        from pcfbench.datasets.av2 import write_av2

        def log_id(s: SequenceData) -> str:  # av2 names are split/log_id already
            return s.name.rpartition("/")[2] if s.name.startswith(f"{s.split}/") else s.name.replace("/", "_")

        named = [SequenceData(log_id(s), s.split if s.split in ("train", "val", "test") else "val", s.T_world_sensor, s.timestamps_ns, s.load) for s in seqs]
        write_av2(out, named, layout="sensor" if layout == "av2-sensor" else "lidar")
    elif layout.startswith("mcap"):
        from pcfbench.datasets.mcap_writer import write_mcap_dataset

        named = [SequenceData(s.name.replace("/", "_"), "all", s.T_world_sensor, s.timestamps_ns, s.load) for s in seqs]
        write_mcap_dataset(out, named, {"mcap": "ros2", "mcap-foxglove": "protobuf", "mcap-json": "json"}[layout])
    else:
        raise PcfbenchError(f"unknown layout {layout!r} (known: {', '.join(LAYOUTS)})")
    return [(a.name, b.name) for a, b in zip(seqs, named)]


def convert(source: str, target: str, splits: tuple[str, ...] = ()) -> list[tuple[str, str]]:
    """Convert dataset ``NAME=ROOT`` into ``LAYOUT=OUT``; returns the sequence name mapping."""
    layout, sep, out = target.partition("=")
    if not sep or not out:
        raise PcfbenchError(f"--to {target!r}: expected LAYOUT=OUT")
    if layout not in LAYOUTS:
        raise PcfbenchError(f"unknown layout {layout!r} (known: {', '.join(LAYOUTS)})")
    adapter = open_adapter(source)
    seqs = [change_axes(s, type(adapter).axes, LAYOUTS[layout][0]) for s in source_sequences(adapter, splits)]
    if not seqs:
        raise PcfbenchError(f"{source}: no sequences to convert")
    return write_layout(layout, Path(out), seqs)


def add_commands(cli) -> None:
    @cli.command(name="convert")
    @click.option("--from", "source", required=True, metavar="NAME[=ROOT]", help="Dataset to read (ROOT may end in ?key=value options).")
    @click.option("--to", "target", required=True, metavar="LAYOUT=OUT", help=f"Layout to write: {', '.join(LAYOUTS)}.")
    @click.option("--split", "splits", multiple=True, help="Only these splits of the source (repeatable).")
    def convert_cmd(source, target, splits):
        """Convert a dataset between layouts (sweeps, poses, timestamps; axes re-expressed)."""
        for a, b in convert(source, target, tuple(splits)):
            click.echo(f"{a} -> {b}")

    @cli.command(name="export")
    @click.option("--store", default=None, type=click.Path(file_okay=False),
                  help="Export a run's stored forecasts from this results store: each method is re-run on the cells' "
                       "samples and its forecast written only when its scores equal the stored rows. -d/-s/-m are "
                       "then shell-style patterns that pick cells.")
    @click.option("--dataset", "-d", "datasets", multiple=True, metavar="NAME[=ROOT]",
                  help="Without --store: the dataset (ROOT may end in ?key=value options). With --store: dataset name "
                       "pattern(s).")
    @click.option("--setting", "-s", "settings", multiple=True, help="Without --store: the setting. With --store: pattern(s).")
    @click.option("--method", "-m", "methods", multiple=True, metavar="NAME[:k=v,...]",
                  help="Without --store: a method variant to run (repeatable). With --store: method name pattern(s).")
    @click.option("--cell", "cells", multiple=True, metavar="PATTERN",
                  help="With --store: pattern(s) on the cell's folder under the store (kitti/kitti-1s/test/copy-last.*).")
    @click.option("--sample", "sample_ids", multiple=True, metavar="SEQUENCE/INDEX",
                  help="A sample to export (repeatable). Default: with --store every sample the cells hold, "
                       "without it the split's first.")
    @click.option("--samples", "count", type=click.IntRange(min=1), default=None, metavar="N",
                  help="Export the first N samples instead.")
    @click.option("--split", default=None, help="Without --store: the split (default: the dataset's evaluation split).")
    @click.option("--policy", type=click.Choice(["full-context", "every-frame"]), default=None,
                  help="Without --store: the sample policy (default: full-context).")
    @click.option("--per-sample", is_flag=True, help="Write one .mcap per sample into the folder --out (SEQUENCE_INDEX.mcap).")
    @click.option("--out", "-o", required=True, type=click.Path(), help="The .mcap file to write (a folder with --per-sample).")
    def export_cmd(store, datasets, settings, methods, cells, sample_ids, count, split, policy, per_sample, out):
        """Write samples' past sweeps, forecasts and ground truth to MCAP for Foxglove.

        \b
        pcfbench export --store STORE [-d/-s/-m/--cell PATTERN] [--samples N] -o run.mcap
            the forecasts a run scored (re-made, and refused unless they score exactly as stored)
        pcfbench export -d NAME=ROOT -s SETTING -m METHOD [--sample ID] -o sample.mcap
            forecasts made now, without a run

        Several samples in one file each get their own span of the timeline (shifts in the file's
        pcfbench.samples metadata). Topics: /past/points, /ground_truth/points (with the dataset's
        intensity), /forecast/<method>/<option>_<value>/points (with a per-point error), /tf, /ego/*.
        """
        if sample_ids and count:
            raise PcfbenchError("--sample names the samples and --samples N takes the first N: give one of them")
        if store is not None:
            if split or policy:
                raise PcfbenchError("--split and --policy pick samples to make; with --store the cells say them "
                                    "(pick cells with -d/-s/-m/--cell)")
            written, n = export_stored(store, out, datasets, settings, methods, cells, count, sample_ids, per_sample)
        else:
            if cells:
                raise PcfbenchError("--cell picks cells of a results store: pass --store DIR")
            if len(datasets) != 1 or len(settings) != 1:
                raise PcfbenchError("without --store, give one --dataset NAME[=ROOT] and one --setting "
                                    "(or --store DIR to export a run's stored forecasts)")
            written, n = export(datasets[0], settings[0], out, sample_ids, split, methods, policy or "full-context",
                                count, per_sample)
        for path in written:
            click.echo(f"wrote {path}")
        click.echo(f"{len(written)} file(s), {n} point clouds")


def check_out(out: str | Path, per_sample: bool) -> Path:
    """``--out`` as a path, or one error when it is a folder for one file or a file for a folder
    (checked before any work)."""
    out = Path(out)
    if not per_sample and out.is_dir():
        raise PcfbenchError(f"--out {out} is a folder: name the .mcap file to write, or pass --per-sample")
    if per_sample and out.exists() and not out.is_dir():
        raise PcfbenchError(f"--out {out} is a file: with --per-sample it is the folder to write one .mcap per sample into")
    return out


def _write(out: str | Path, items, topics: dict, record: dict, per_sample: bool) -> tuple[list[Path], int]:
    """``items`` (written as they come) into the MCAP ``out``, or one per sample into the folder ``out``."""
    from pcfbench.datasets.export_mcap import per_sample_name, write_mcap

    out = check_out(out, per_sample)
    if not per_sample:
        path, n = write_mcap(out, items, topics, record)
        return [path], n
    written: dict[str, Path] = {}
    total = 0
    for it in items:
        name = per_sample_name(it.sample.sample_id)
        if name in written:
            raise PcfbenchError(f"--per-sample: two samples would share the file name {name}")
        written[name], n = write_mcap(out / name, [it], topics, record)
        total += n
    return list(written.values()), total


def export_stored(store: str | Path, out: str | Path, datasets: tuple[str, ...] = (), settings: tuple[str, ...] = (),
                  methods: tuple[str, ...] = (), cells: tuple[str, ...] = (), count: int | None = None,
                  sample_ids: tuple[str, ...] = (), per_sample: bool = False, plugins=None) -> tuple[list[Path], int]:
    """A run's stored forecasts (the cells of ``store`` the patterns pick; every one checked
    against its stored rows: :mod:`pcfbench.datasets.export_forecasts`) to ``out``; returns the
    files written and the number of point clouds."""
    from pcfbench.datasets.export_forecasts import stored_forecasts
    from pcfbench.reporting.select import Selection

    import os

    from tqdm import tqdm

    check_out(out, per_sample)
    selection = Selection(tuple(datasets), tuple(settings), tuple(methods))
    bar = None

    def progress(done: int, total: int) -> None:
        nonlocal bar
        if bar is None:
            bar = tqdm(total=total, desc="re-making the stored forecasts", unit="sample",
                       disable=True if os.environ.get("CI") or os.environ.get("PCFBENCH_NO_PROGRESS") else None)
        bar.update(1)

    try:
        items, topics, record = stored_forecasts(Path(store), selection, tuple(cells), count, tuple(sample_ids), plugins,
                                                 progress)
        return _write(out, items, topics, record, per_sample)
    finally:
        if bar is not None:
            bar.close()


def check_sample(builder, split: str, sample_id: str, where: str = "--sample") -> tuple[str, int]:
    """``sample_id`` (SEQUENCE/INDEX) as a key of ``builder``'s samples of ``split``, or one
    error saying what is wrong with it: not SEQUENCE/INDEX, an unknown sequence, an index past
    the sequence's end, or too little past (or future) for the setting."""
    adapter, s = builder.adapter, builder.setting
    hint = f"`pcfbench ls samples {adapter.name}=ROOT --setting {s.name} --split {split}` lists the valid ids"
    seq, _, idx = str(sample_id).rpartition("/")
    if not seq or not idx.isdigit():
        raise PcfbenchError(f"{where} {sample_id!r}: expected SEQUENCE/INDEX, e.g. 08/000010; {hint}")
    index = int(idx)
    names = list(adapter.sequence_names(split))
    if not names:  # which split its sequences are in, rather than "it has" nothing
        from pcfbench.protocol.nosamples import no_sequences

        raise PcfbenchError(no_sequences(adapter, split, f"{where} {sample_id!r}: {adapter.name}:{split} has no "
                                                         "sequence").message)
    if seq not in names:
        shown = ", ".join(names[:8]) + (f", ... ({len(names)} in all)" if len(names) > 8 else "")
        raise PcfbenchError(f"{where} {sample_id!r}: {adapter.name}:{split} has no sequence {seq!r} (it has {shown}); {hint}")
    keys = [i for q, i in builder.sample_keys(split) if q == seq]
    if index in keys:
        return seq, index
    n = len(builder.sequence(seq))
    if index >= n:
        raise PcfbenchError(f"{where} {sample_id!r}: sequence {seq} has {n} sweeps (indices 0..{n - 1}); {hint}")
    span = f"valid indices of sequence {seq}: {keys[0]}..{keys[-1]}" if keys else f"sequence {seq} has no valid sample"
    first_ok = (s.past - 1) * s.stride
    if index < first_ok:
        why = (f"not enough past for {s.name}: it needs {s.past - 1} past sweeps {s.stride} apart before the "
               f"reference, so the index must be at least {first_ok}")
    elif index > n - 1 - s.future * s.stride:
        why = (f"not enough future for {s.name}: it needs {s.future} future sweeps {s.stride} apart after the "
               f"reference, and sequence {seq} ends at {n - 1}")
    else:
        why = f"not one of the samples of the sample policy {builder.policy}"
    raise PcfbenchError(f"{where} {sample_id!r}: {why} ({span}); {hint}")


def export(dataset: str, setting: str, out: str | Path, sample_ids: tuple[str, ...] | str | None = (),
           split: str | None = None, methods: tuple[str, ...] = (), policy: str = "full-context", count: int | None = None,
           per_sample: bool = False) -> tuple[list[Path], int]:
    """Write samples (``sample_ids``; else the first ``count``; else the split's first), their
    ground truth and each method variant's forecast made now (scored) to the MCAP ``out`` (one
    per sample into the folder ``out`` with ``per_sample``); returns the files and the number
    of point clouds."""
    from pcfbench.metrics.base import score_sample
    from pcfbench.method import resolve_method
    from pcfbench.plugins import get_plugins
    from pcfbench.plugins import get_setting
    from pcfbench.protocol import SampleBuilder, check_compatible
    from pcfbench.running.runner import default_metrics
    from pcfbench.protocol.validate import validate_forecast
    from pcfbench.datasets.export_forecasts import sample_intensity
    from pcfbench.datasets.export_mcap import SampleExport, forecast_topic, unique_topics

    if isinstance(sample_ids, str):
        sample_ids = (sample_ids,)
    check_out(out, per_sample)
    plugins = get_plugins()
    resolved = [resolve_method(spec, plugins) for spec in methods]  # a bad spec fails before any work
    seen: dict[tuple[str, str], str] = {}
    for m, spec in zip(resolved, methods):
        key = (m.name, m.options_hash)
        if key in seen:
            raise PcfbenchError(f"--method {spec!r} is the same variant as {seen[key]!r} (same method and options): "
                                "give each variant once")
        seen[key] = spec
    labels = [m.name + (":" + ",".join(f"{k}={v}" for k, v in sorted(dict(m.raw).items())) if m.raw else "") for m in resolved]
    topics = unique_topics({label: forecast_topic(m.name, dict(m.raw)) for label, m in zip(labels, resolved)})
    adapter = open_adapter(dataset)
    s = get_setting(setting)
    check_compatible(s, adapter)
    builder = SampleBuilder(adapter, s, policy)
    split = split or type(adapter).default_split
    if split not in adapter.splits():
        from pcfbench.errors import unknown_name

        raise unknown_name(f"split of dataset {adapter.name}", split, adapter.splits())
    if sample_ids:
        keys = [check_sample(builder, split, sid) for sid in sample_ids]
    else:
        keys = builder.sample_keys(split)
        if not keys:
            from pcfbench.protocol.nosamples import explain

            settings = [get_setting(name, plugins) for name in type(adapter).default_settings]
            raise PcfbenchError(explain(builder, split, settings=settings).message)
        keys = keys[: count or 1]
    metrics = [plugins.metrics.get(m) for m in default_metrics(plugins)]
    instances = [m.create() for m in resolved]

    def items():
        for seq, index in keys:
            sample, truth = builder.build(seq, index)
            forecasts, scores = {}, {}
            for label, method in zip(labels, instances):
                fc = validate_forecast(sample, method.forecast(sample.for_method()))
                forecasts[topics[label]] = fc
                scores[topics[label]] = score_sample(sample, truth, fc, metrics, protocol=builder.protocol)
            intensity = sample_intensity(builder, sample, truth)
            yield SampleExport(sample, truth, forecasts, scores, {}, *(intensity or (None, None)))

    record = {"source": "recomputed (no results store)", "split": split, "setting": setting, "policy": policy,
              "metric_versions": ", ".join(f"{m.name} v{m.version}" for m in metrics)}
    described = {topics[label]: {"method": m.name, "options": dict(m.raw), "spec": label} for label, m in zip(labels, resolved)}
    return _write(out, items(), described, record, per_sample)
