"""Generating a domain: simulate every sequence, write it through a layout writer, cache it.

``simulate_sequence`` is pure (domain + sequence index -> sweeps, poses, labels); layout
writers turn one simulated sequence into files; ``ensure_domain`` keeps a complete,
versioned copy under ``pcfbench.config.cache_dir() / "synthetic"`` and regenerates a copy whose
completion marker is missing (an interrupted generation).
"""

from __future__ import annotations

import json
import os
import shutil
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from pcfbench.errors import PcfbenchError, UnknownNameError
from pcfbench.running.warmup import preparing_data
from pcfbench.datasets.synthetic.domains import GENERATOR_VERSION, Domain, get_domain
from pcfbench.datasets.synthetic.lidar import EGO_SHAPE, StaticScene, cast_sweep
from pcfbench.datasets.synthetic.world import (
    CLASS_NAMES, TRUNK, VEGETATION, Ground, build_static, make_agents, make_road_graph, make_route, speed_profile,
)

MANIFEST = "synthetic.json"
COMPLETE = ".complete"


def trunk_class(domain: Domain) -> int:
    """The class of tree trunks: TRUNK where the domain's physics makes them solid (4 and
    later), else VEGETATION (physics 1's bytes and manifests stay as they were)."""
    return TRUNK if domain.realism is not None and domain.realism.solid_trunks else VEGETATION


@dataclass
class SimulatedSequence:
    domain: str
    name: str
    split: str
    points: list[np.ndarray]  # sensor frame, float32 (N, 3)
    intensity: list[np.ndarray]
    labels: list[np.ndarray]  # uint32 class | instance << 16 (SemanticKITTI convention)
    T_world_sensor: np.ndarray  # (T, 4, 4)
    times_s: np.ndarray  # (T,)
    stats: dict = field(default_factory=dict)


def _rot(yaw: float, pitch: float, roll: float) -> np.ndarray:
    cy, sy, cp, sp, cr, sr = np.cos(yaw), np.sin(yaw), np.cos(pitch), np.sin(pitch), np.cos(roll), np.sin(roll)
    Rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    Ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    Rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    return Rz @ Ry @ Rx


def ego_poses(domain: Domain, ground: Ground, route, s_t: np.ndarray, times: np.ndarray, t_start: float) -> np.ndarray:
    """(T, 4, 4) sensor poses: on the route, on the ground, pitched and rolled with the slope."""
    out = np.tile(np.eye(4), (len(times), 1, 1))
    for k, t in enumerate(times):
        i = min((t + t_start) / 0.01, len(s_t) - 1.0)
        s = np.interp(i, np.arange(len(s_t)), s_t)
        (x, y), yaw = route.at(s)
        c, sn = np.cos(yaw), np.sin(yaw)
        h = lambda dx, dy: float(ground.undulation(np.array(x + dx), np.array(y + dy)))  # noqa: E731
        pitch = -np.arctan((h(1.5 * c, 1.5 * sn) - h(-1.5 * c, -1.5 * sn)) / 3.0)
        roll = np.arctan((h(-0.8 * sn, 0.8 * c) - h(0.8 * sn, -0.8 * c)) / 1.6)
        R = _rot(float(yaw), pitch, roll)
        out[k, :3, :3] = R
        out[k, :3, 3] = np.array([x, y, h(0, 0)]) + R @ np.array([0.0, 0.0, domain.sensor.mount_height_m])
    return out


def simulate_sequence(domain: Domain, name: str, progress: Callable[[int], None] | None = None) -> SimulatedSequence:
    """Simulate one sequence of ``domain`` (deterministic in the domain seed and sequence index)."""
    index = domain.sequence_index(name)
    split, _, num = domain.sequences()[index]
    seeds = np.random.SeedSequence([domain.seed, index]).spawn(5)
    rng_world, rng_ego, rng_static, rng_agents, rng_sensor = (np.random.default_rng(s) for s in seeds)
    style = domain.style
    if domain.realism is not None:  # physics 6 narrows the sidewalk; physics 1 keeps the style as it is
        from pcfbench.datasets.synthetic import realism as physics2

        style = physics2.street_style(style, domain.realism)
    duration = (num - 1) / domain.rate_hz
    graph = make_road_graph(style, rng_world)
    ground = Ground(style, graph, rng_world)
    cruise = rng_ego.uniform(*style.ego_speed_mps)
    t_start = rng_ego.uniform(0.0, 3.0)
    route = make_route(graph, rng_ego, style.ego_speed_mps[1] * 1.2 * (duration + t_start) + 40.0, style.lane_width_m / 2)
    s_t, _ = speed_profile(route, rng_ego, cruise, style.stop_prob, duration=duration + t_start + 0.1)
    times = np.arange(num) / domain.rate_hz
    T = ego_poses(domain, ground, route, s_t, times, t_start)
    margin = domain.sensor.max_range_m + 10.0
    lo = T[:, :2, 3].min(0) - margin
    hi = T[:, :2, 3].max(0) + margin
    soup = build_static(style, graph, ground, rng_static, lo, hi,
                        clearance=None if domain.realism is None else domain.realism.clearance_m,
                        trunk_class=trunk_class(domain))
    if domain.realism is not None:  # its own stream: physics 1 draws stay as they were
        physics2.add_shrubs(soup, style, graph, ground, np.random.default_rng([domain.seed, index, 2]), lo, hi, domain.realism)
    static = StaticScene(soup)
    traffic = style if domain.realism is None else physics2.with_traffic(style, domain.realism)
    agents = make_agents(traffic, graph, rng_agents, lo, hi, duration + t_start)
    for a in agents:
        a.t0 += t_start
    # No collisions with the ego vehicle: agents that would come within 3.5 m of it are left out.
    fine_t = np.arange(0.0, duration + 1e-9, 0.05)
    fine_T = ego_poses(domain, ground, route, s_t, fine_t, t_start)[:, :2, 3]
    agents = [a for a in agents if np.min(np.linalg.norm(a.positions(fine_t) - fine_T, axis=1)) > 3.5]
    directions = domain.sensor.directions()
    seq = SimulatedSequence(domain.name, name, split, [], [], [], T, times)
    hits = drops = 0
    if domain.realism is not None:
        calibration = physics2.beam_calibration(domain.sensor, domain.realism, domain.seed)
        fire = physics2.column_times(domain.sensor, domain.realism)
        half = domain.realism.revolution_s / 2
    for k, t in enumerate(times):
        if domain.realism is None:
            res = cast_sweep(domain.sensor, static, agents, ground, float(t), T[k], rng_sensor, directions)
        else:
            sub = float(t) + np.linspace(-half, half, 33)
            col_T = physics2.interpolate_poses(sub, ego_poses(domain, ground, route, s_t, sub, t_start), float(t) + fire)
            res = physics2.cast_sweep_realistic(domain.sensor, static, agents, ground, float(t), col_T, rng_sensor,
                                                calibration, domain.realism)
        seq.points.append(res.points)
        seq.intensity.append(res.intensity)
        seq.labels.append(res.labels | (res.instance << np.uint32(16)))
        hits += res.rays_hit
        drops += res.rays_dropped
        if progress:
            progress(1)
    if domain.realism is not None:  # stored poses are estimates (realism.stored_poses)
        seq.T_world_sensor = physics2.stored_poses(T, times, domain.realism, np.random.default_rng([domain.seed, index, 3]))
    seq.stats = {
        "sweeps": num,
        "mean_points": float(np.mean([len(p) for p in seq.points])),
        "drop_rate": drops / max(hits, 1),
        "agents": len(agents),
        "path_length_m": float(np.sum(np.linalg.norm(np.diff(T[:, :3, 3], axis=0), axis=1))),
    }
    return seq


# --- layout writers ----------------------------------------------------------------------------

def write_kitti(root: Path, seq: SimulatedSequence) -> None:
    """KITTI Odometry layout (plus SemanticKITTI-style ``labels/NNNNNN.label``)."""
    from pcfbench.datasets.kitti import write_kitti_sequence

    seq_dir = write_kitti_sequence(root, seq.name, seq.points, seq.T_world_sensor, seq.times_s, intensity=seq.intensity)
    labels = seq_dir / "labels"
    labels.mkdir(exist_ok=True)
    for i, lab in enumerate(seq.labels):
        np.asarray(lab, np.uint32).tofile(labels / f"{i:06d}.label")


#: Epoch of the first sweep of sequence k in layouts that store absolute times (not KITTI).
EPOCH_NS = 1_600_000_000 * 10**9


def _other_layouts() -> dict[str, str]:
    """Layouts of the adapters' shared writer (``pcfbench.datasets.commands.write_layout``) -> axes."""
    try:
        from pcfbench.datasets.commands import LAYOUTS
    except ImportError:
        return {}
    return {name: axes for name, (axes, _) in LAYOUTS.items() if name != "kitti"}


def available_layouts() -> tuple[str, ...]:
    return ("kitti", *_other_layouts())


def write_other_layout(layout: str, out: Path, seqs: list[SimulatedSequence], domain: Domain) -> dict[str, str]:
    """Write simulated sequences through the adapters' writer; returns source -> written names.

    Sensor frames are re-expressed in the layout's axis convention; times become absolute.
    """
    from pcfbench.datasets.commands import write_layout
    from pcfbench.datasets.layout import STANDARD_AXES, SequenceData, change_axes

    data = []
    for seq in seqs:
        k = domain.sequence_index(seq.name)
        ts = EPOCH_NS + k * 10**12 + np.round(seq.times_s * 1e9).astype(np.int64)
        sd = SequenceData.from_arrays(seq.name, seq.split, seq.points, seq.T_world_sensor, ts)
        data.append(change_axes(sd, STANDARD_AXES, _other_layouts()[layout]))
    return dict(write_layout(layout, Path(out), data))


def get_writer(layout: str) -> str:
    """Validate ``layout``: ``kitti`` always, the others when the adapters' writers are installed."""
    if layout in available_layouts():
        return layout
    if layout in ("nuscenes", "av2", "mcap"):
        raise PcfbenchError(f"layout {layout!r} has no writer in this install (available: {', '.join(available_layouts())})")
    raise UnknownNameError(f"unknown layout {layout!r} (known: {', '.join(available_layouts())})")


def _progress_bar(total: int, desc: str, enabled: bool):
    from tqdm import tqdm

    return tqdm(total=total, desc=desc, unit="sweep", disable=not enabled or None, leave=True, dynamic_ncols=True,
                file=sys.stderr)


def generate_domain(domain: Domain | str, out: str | Path, layout: str = "kitti", progress: bool = True,
                    splits: tuple[str, ...] | None = None) -> dict:
    """Write every sequence of ``domain`` (or only ``splits``) under ``out``; returns the manifest."""
    domain = get_domain(domain) if isinstance(domain, str) else domain
    get_writer(layout)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    todo = [(sp, n, k) for sp, n, k in domain.sequences() if splits is None or sp in splits]
    if splits is not None:
        unknown = set(splits) - set(domain.splits)
        if unknown:
            raise UnknownNameError(f"domain {domain.name!r} has no split(s) {sorted(unknown)} (known: {', '.join(domain.splits)})")
    manifest = {
        "domain": domain.name, "generator_version": GENERATOR_VERSION, "seed": domain.seed, "layout": layout,
        "sensor": domain.sensor.name, "beams": domain.sensor.beams, "rate_hz": domain.rate_hz,
        "splits": {sp: [n for s2, n, _ in todo if s2 == sp] for sp in domain.splits},
        "classes": list(CLASS_NAMES if trunk_class(domain) == TRUNK else CLASS_NAMES[:TRUNK]),
        "ego_shape": {"x_min": EGO_SHAPE.x_min, "x_max": EGO_SHAPE.x_max, "half_width": EGO_SHAPE.half_width},
        "sequences": {},
    }
    if domain.realism is not None:  # physics version 1 manifests stay as they were
        manifest["physics"] = domain.physics
    kept = _splits_kept(out, manifest, layout, splits)
    started = time.perf_counter()
    held = []  # other layouts write all sequences at once
    with _progress_bar(sum(k for _, _, k in todo), f"generating {domain.name}", progress) as bar:
        for split, name, _ in todo:
            seq = simulate_sequence(domain, name, progress=bar.update)
            if layout == "kitti":
                write_kitti(out, seq)
            else:
                held.append(seq)
            manifest["sequences"][name] = {"split": split, **seq.stats}
    if held:
        manifest["written_as"] = write_other_layout(layout, out, held, domain)
    manifest["seconds"] = round(time.perf_counter() - started, 2)
    if kept:  # the folder's other splits stay listed (same world, generated before)
        _merge_manifest(out, manifest)
    else:
        (out / MANIFEST).write_text(json.dumps({k: v for k, v in manifest.items() if k != "seconds"}, indent=1, sort_keys=True) + "\n")
    return manifest


#: What makes a folder's sweeps one world: generating some splits into a folder that holds
#: others keeps them only when these agree (else the folder would mix two worlds).
WORLD_KEYS = ("domain", "generator_version", "seed", "layout", "sensor", "beams", "rate_hz", "physics")


def _splits_kept(out: Path, manifest: dict, layout: str, splits: tuple[str, ...] | None) -> bool:
    """Whether ``out`` already holds other splits of the same world (KITTI layout), to be kept in
    its manifest beside the ones generated now. A folder that holds another world's splits is
    refused before anything is written."""
    path = out / MANIFEST
    if splits is None or layout != "kitti" or not path.is_file():
        return False
    try:
        old = json.loads(path.read_text())
        others = {n: m for n, m in old.get("sequences", {}).items() if m.get("split") not in splits}
    except (OSError, ValueError, AttributeError) as exc:
        raise PcfbenchError(f"{path}: not a readable synthetic manifest ({exc}); generating into {out} would "
                            "leave its splits unlisted: use an empty folder") from None
    if not others:
        return False
    differ = [k for k in WORLD_KEYS if old.get(k) != manifest.get(k)]
    if differ:
        raise PcfbenchError(
            f"{out} holds split(s) {', '.join(sorted({m['split'] for m in others.values()}))} of another world "
            f"({'; '.join(f'{k} {old.get(k)!r} there, {manifest.get(k)!r} now' for k in differ)}): generating "
            f"{', '.join(splits)} into it would mix the two; use an empty folder or generate every split")
    return True


# --- the cache ---------------------------------------------------------------------------------
#
# One KITTI-layout root per domain and generator version. Splits are generated on first use,
# each into a temporary folder that is moved in and then marked complete (``.complete-<split>``);
# a split without its marker (an interrupted generation) is removed and generated again.

MANAGED = ".pcfbench-synthetic-cache"


def cache_root(domain: Domain) -> Path:
    from pcfbench.config import cache_dir

    physics = "" if domain.physics == 1 else f"-physics{domain.physics}"  # physics 1 folders stay put
    return cache_dir() / "synthetic" / f"{domain.name}-v{GENERATOR_VERSION}{physics}"


def split_complete(root: Path, split: str) -> bool:
    return (Path(root) / f"{COMPLETE}-{split}").is_file()


def is_managed(root: Path) -> bool:
    return (Path(root) / MANAGED).is_file()


def _check_writable(folder: Path) -> None:
    try:
        folder.mkdir(parents=True, exist_ok=True)
        probe = folder / f".write-test-{os.getpid()}"
        probe.write_text("")
        probe.unlink()
    except OSError as exc:
        raise PcfbenchError(
            f"cannot write the synthetic data cache {folder} ({exc.strerror or exc}): "
            "set PCFBENCH_CACHE to a writable folder"
        ) from None


def ensure_domain(domain: Domain | str, splits: tuple[str, ...] | None = None, progress: bool = True,
                  root: Path | None = None) -> Path:
    """The cached KITTI-layout root of ``domain`` with ``splits`` (default: all) complete.

    Generates what is missing (under a lock, so concurrent runs do not collide) and prints
    where. ``root`` overrides the cache location (tests).
    """
    domain = get_domain(domain) if isinstance(domain, str) else domain
    splits = tuple(domain.splits) if splits is None else tuple(splits)
    unknown = [sp for sp in splits if sp not in domain.splits]
    if unknown:
        raise UnknownNameError(f"domain {domain.name!r} has no split(s) {unknown} (known: {', '.join(domain.splits)})")
    final = Path(root) if root is not None else cache_root(domain)
    if all(split_complete(final, sp) for sp in splits):
        return final
    _check_writable(final.parent)
    import fcntl

    with open(final.parent / f".{final.name}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # another process may be generating the same domain
        if final.exists() and not is_managed(final):
            raise PcfbenchError(f"{final} exists but is not a pcfbench synthetic cache: move it or set PCFBENCH_CACHE")
        if not final.exists():
            final.mkdir(parents=True)
            (final / MANAGED).write_text(json.dumps({"domain": domain.name, "generator_version": GENERATOR_VERSION}) + "\n")
        for split in splits:
            if split_complete(final, split):
                continue
            names = [n for n, _ in domain.splits[split]]
            partial = [n for n in names if (final / "sequences" / n).exists() or (final / "poses" / f"{n}.txt").exists()]
            if partial:
                print(f"pcfbench: {final}: split {split!r} is incomplete (interrupted generation?): regenerating it",
                      file=sys.stderr)
                for n in partial:
                    shutil.rmtree(final / "sequences" / n, ignore_errors=True)
                    (final / "poses" / f"{n}.txt").unlink(missing_ok=True)
            for stale in final.parent.glob(f"{final.name}.tmp-*-{split}"):
                shutil.rmtree(stale, ignore_errors=True)
            tmp = final.parent / f"{final.name}.tmp-{os.getpid()}-{split}"
            print(f"pcfbench: generating {domain.name} split {split!r} into {final} "
                  "(once; set PCFBENCH_CACHE to move it)", file=sys.stderr)
            preparing_data()  # a run's kernel warm-up takes the core this leaves idle (pcfbench.running.warmup)
            manifest = generate_domain(domain, tmp, "kitti", progress=progress, splits=(split,))
            (final / "sequences").mkdir(exist_ok=True)
            (final / "poses").mkdir(exist_ok=True)
            for n in names:
                os.replace(tmp / "sequences" / n, final / "sequences" / n)
                os.replace(tmp / "poses" / f"{n}.txt", final / "poses" / f"{n}.txt")
            _merge_manifest(final, manifest)
            shutil.rmtree(tmp)
            (final / f"{COMPLETE}-{split}").write_text(json.dumps({"seconds": manifest["seconds"]}) + "\n")
            print(f"pcfbench: {domain.name} split {split!r} ready in {manifest['seconds']:.0f} s", file=sys.stderr)
    return final


def _merge_manifest(root: Path, manifest: dict) -> None:
    path = root / MANIFEST
    old = json.loads(path.read_text()) if path.is_file() else {}
    merged = {k: v for k, v in manifest.items() if k not in ("seconds", "splits", "sequences")}
    merged["sequences"] = {**old.get("sequences", {}), **manifest["sequences"]}
    merged["splits"] = {sp: sorted(n for n, m in merged["sequences"].items() if m["split"] == sp)
                        for sp in manifest["splits"]}
    tmp = root / f".{MANIFEST}.tmp"
    tmp.write_text(json.dumps(merged, indent=1, sort_keys=True) + "\n")
    os.replace(tmp, path)
