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
    @click.option("--dataset", "-d", "dataset", required=True, metavar="NAME[=ROOT]")
    @click.option("--setting", "-s", required=True)
    @click.option("--sample", "sample_id", default=None, help="Sample id SEQUENCE/INDEX (default: the split's first sample).")
    @click.option("--split", default=None, help="Split (default: the dataset's evaluation split).")
    @click.option("--method", "-m", "methods", multiple=True, metavar="NAME[:k=v,...]", help="Method whose forecast to include (repeatable).")
    @click.option("--policy", type=click.Choice(["full-context", "every-frame"]), default="full-context", show_default=True)
    @click.option("--out", "-o", required=True, type=click.Path(dir_okay=False), help="The .mcap file to write.")
    def export_cmd(dataset, setting, sample_id, split, methods, policy, out):
        """Write a sample's past sweeps, forecasts and ground truth to an MCAP for Foxglove."""
        path, n = export(dataset, setting, out, sample_id, split, methods, policy)
        click.echo(f"wrote {path} ({n} point clouds)")


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


def variant_topic(method) -> str:
    """A method variant's topic name: its spec as on the command line (``raycast-voxel:voxel=0.4``),
    the bare name without options, so two options of one method never share a topic."""
    raw = dict(method.raw)
    return method.name + (":" + ",".join(f"{k}={v}" for k, v in sorted(raw.items())) if raw else "")


def export(dataset: str, setting: str, out: str | Path, sample_id: str | None = None, split: str | None = None,
           methods: tuple[str, ...] = (), policy: str = "full-context") -> tuple[Path, int]:
    """Write one sample, its ground truth and each method variant's forecast (scored) to the MCAP
    ``out``; returns the path and the number of point clouds."""
    from pcfbench.metrics.base import score_sample
    from pcfbench.method import resolve_method
    from pcfbench.plugins import get_plugins
    from pcfbench.plugins import get_setting
    from pcfbench.protocol import SampleBuilder, check_compatible
    from pcfbench.running.runner import default_metrics
    from pcfbench.protocol.validate import validate_forecast
    from pcfbench.datasets.export_mcap import export_sample

    plugins = get_plugins()
    resolved = [resolve_method(spec, plugins) for spec in methods]  # a bad spec fails before any work
    topics = [variant_topic(m) for m in resolved]
    seen: dict[tuple[str, str], str] = {}
    for m, spec in zip(resolved, methods):
        key = (m.name, m.options_hash)
        if key in seen:
            raise PcfbenchError(f"--method {spec!r} is the same variant as {seen[key]!r} (same method and options): "
                                "give each variant once")
        seen[key] = spec
    adapter = open_adapter(dataset)
    s = get_setting(setting)
    check_compatible(s, adapter)
    builder = SampleBuilder(adapter, s, policy)
    split = split or type(adapter).default_split
    if split not in adapter.splits():
        from pcfbench.errors import unknown_name

        raise unknown_name(f"split of dataset {adapter.name}", split, adapter.splits())
    if sample_id is None:
        keys = builder.sample_keys(split)
        if not keys:
            from pcfbench.protocol.nosamples import explain

            settings = [get_setting(name, plugins) for name in type(adapter).default_settings]
            raise PcfbenchError(explain(builder, split, settings=settings).message)
        seq, index = keys[0]
    else:
        seq, index = check_sample(builder, split, sample_id)
    sample, truth = builder.build(seq, index)
    metrics = [plugins.metrics.get(m) for m in default_metrics(plugins)]
    forecasts, scores = {}, {}
    for topic, method in zip(topics, resolved):
        fc = validate_forecast(sample, method.create().forecast(sample.for_method()))
        forecasts[topic] = fc
        scores[topic] = score_sample(sample, truth, fc, metrics)
    meta = {"split": split, "setting": setting, "policy": policy,
            "metric_versions": ", ".join(f"{m.name} v{m.version}" for m in metrics)}
    path = export_sample(out, sample, truth, forecasts, metadata=meta, scores=scores)
    return path, len(sample.past_points_ref) + len(truth.future_points_ref) * (1 + len(forecasts))
