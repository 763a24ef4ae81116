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


def export(dataset: str, setting: str, out: str | Path, sample_id: str | None = None, split: str | None = None,
           methods: tuple[str, ...] = (), policy: str = "full-context") -> tuple[Path, int]:
    from pcfbench.method import resolve_method
    from pcfbench.plugins import get_plugins
    from pcfbench.protocol import SampleBuilder, check_compatible, get_setting
    from pcfbench.validate import validate_forecast
    from pcfbench.datasets.export_mcap import export_sample

    resolved = [resolve_method(spec, get_plugins()) for spec in methods]  # a bad spec fails before any work
    names = [method.name for method in resolved]
    if len(set(names)) < len(names):
        raise PcfbenchError(f"--method: each method can be exported once (its name is its MCAP topic), got {', '.join(methods)}")
    adapter = open_adapter(dataset)
    s = get_setting(setting)
    check_compatible(s, adapter)
    builder = SampleBuilder(adapter, s, policy)
    if sample_id is None:
        keys = builder.sample_keys(split or type(adapter).default_split)
        if not keys:
            raise PcfbenchError(f"{dataset}: no samples for setting {setting} ({policy})")
        seq, index = keys[0]
    else:
        seq, _, idx = sample_id.rpartition("/")
        if not seq or not idx.isdigit():
            raise PcfbenchError(f"--sample {sample_id!r}: expected SEQUENCE/INDEX, e.g. scene-0003/000005")
        index = int(idx)
    sample, truth = builder.build(seq, index)
    forecasts = {method.name: validate_forecast(sample, method.create().forecast(sample.for_method())) for method in resolved}
    path = export_sample(out, sample, truth, forecasts)
    return path, len(sample.past_points_ref) + len(truth.future_points_ref) * (1 + len(forecasts))
