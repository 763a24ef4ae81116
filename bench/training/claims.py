"""What a checkpoint's manifest claims, checked before a cell believes it: the steps it was
trained against those planned, its training data by content where that data is at hand
(else marked unverified), and how much of an evaluated split is in its training data by
content, whatever the data's names."""

from __future__ import annotations

import os
from pathlib import Path
from typing import TYPE_CHECKING, Any, Iterable

if TYPE_CHECKING:  # pragma: no cover
    from pcfbench.dataset import DataFingerprint
    from pcfbench.plugins import Plugins
    from pcfbench.training.checkpoints import Checkpoint

#: Hex digits of each training file's sha256 a manifest keeps (``train_files_sha256``).
SHA_DIGITS = 16
#: An evaluated split with at least this share of its bytes in a checkpoint's training data
#: (identical files, by content) is its training data: a copy of the test sweeps renamed
#: into a training split included. Small side files (a calibration, a times file) can be
#: equal by chance across splits (3 of the 23 files of a 24-sweep test KITTI tree, 1 % of its
#: bytes); sweeps cannot.
OVERLAP_FRACTION = 0.10


def train_files_sha256(paths: Iterable[str | Path]) -> list[str]:
    """The sorted, distinct content hashes (``SHA_DIGITS`` hex digits) of the training files,
    from the content-hash cache where it has them (:mod:`pcfbench.contenthash`)."""
    from pcfbench.contenthash import hash_files

    items = [(Path(p), os.stat(p)) for p in paths]
    return sorted({sha[:SHA_DIGITS] for sha in hash_files(items).values()})


def steps_record(ck: "Checkpoint") -> dict[str, Any]:
    """Steps trained, steps planned (None: a manifest from before they were recorded) and
    whether the training finished."""
    planned = ck.manifest.get("steps_planned")
    return {"trained": ck.steps, "planned": planned if isinstance(planned, int) else None,
            "complete": bool(ck.manifest.get("complete"))}


def overlap(ck: "Checkpoint", fingerprint: "DataFingerprint") -> dict[str, Any] | None:
    """How much of the evaluated files (``fingerprint``) is in the checkpoint's training data,
    by content: files and share of bytes; None when the manifest records no content."""
    trained = ck.manifest.get("train_files_sha256")
    if not isinstance(trained, list):
        return None
    trained = set(trained)
    shared = [f for f in fingerprint.files if f[3][:SHA_DIGITS] in trained]
    total = sum(f[1] for f in fingerprint.files)
    return {"files": len(shared), "of": len(fingerprint.files),
            "bytes_fraction": (sum(f[1] for f in shared) / total) if total else 0.0}


def verify_training_data(ck: "Checkpoint", plugins: "Plugins | None" = None) -> dict[str, str]:
    """Whether the manifest's training data (dataset, split, root, fingerprint) is what it
    claims: ``verified`` when that data is at hand and its content fingerprint is the one
    recorded (or, for a shipped checkpoint of made data, its recipe is today's); ``differs``
    when the data at hand is other data; ``unverified`` when it is not at hand. ``why`` says
    which."""
    from pcfbench.dataset import FINGERPRINT_KIND
    from pcfbench.plugins import get_plugins
    from pcfbench.training.data import data_recipe_sha256

    t = ck.train_on
    label = f"{t.get('dataset')}:{t.get('split')}"
    shipped = ck.manifest.get("shipped") if isinstance(ck.manifest.get("shipped"), dict) else None
    recipe = shipped.get("data_recipe_sha256") if shipped else None
    if recipe and not t.get("dataset_options"):
        try:
            if data_recipe_sha256(str(t.get("dataset")), str(t.get("split")), plugins) == recipe:
                return {"status": "verified", "why": f"{label} is made by the recipe it was trained on"}
        except Exception:  # noqa: BLE001 - an unknown dataset: not verified, said below
            pass
    root = t.get("root")
    if t.get("fingerprint_kind") != FINGERPRINT_KIND:
        return {"status": "unverified", "why": f"its manifest records {label} by file sizes and times, not content"}
    if not root or not Path(root).exists():
        return {"status": "unverified", "why": f"its training data {label} ({root}) is not at hand"}
    try:
        cls = (plugins or get_plugins()).datasets.get(str(t["dataset"]))
        adapter = cls(root, **{k: str(v) for k, v in (t.get("dataset_options") or {}).items()})
        digest = adapter.fingerprint(str(t["split"])).digest
    except Exception as exc:  # noqa: BLE001 - whatever stops the check leaves the claim unverified
        return {"status": "unverified", "why": f"its training data {label} at {root} cannot be read ({exc})"}
    if digest != t.get("fingerprint"):
        return {"status": "differs", "why": f"{label} at {root} is not the data its manifest records (fingerprint "
                                            f"{t.get('fingerprint')}, here {digest}): edited since, or another claim"}
    return {"status": "verified", "why": f"{label} at {root} has the content its manifest records"}


def claims_meta(ck: "Checkpoint", fingerprint: "DataFingerprint", plugins: "Plugins | None" = None) -> dict[str, Any]:
    """What a trained method's cell.json records of its checkpoint's claims (not identity):
    ``checkpoint_steps``, ``training_data_check`` and ``training_data_overlap``."""
    return {"checkpoint_steps": steps_record(ck), "training_data_check": verify_training_data(ck, plugins),
            "training_data_overlap": overlap(ck, fingerprint)}


def claim_marks(meta: dict[str, Any]) -> list[str]:
    """What a reader must see of a cell's checkpoint claims: an unfinished training (steps of
    steps planned) and training data that could not be verified, or differs."""
    marks = []
    steps = meta.get("checkpoint_steps") or {}
    if steps and not steps.get("complete"):
        planned = steps.get("planned")
        marks.append(f"UNFINISHED {steps.get('trained')} of {planned} steps" if planned
                     else f"UNFINISHED at {steps.get('trained')} steps")
    check = (meta.get("training_data_check") or {}).get("status")
    if check == "unverified":
        marks.append("training data unverified")
    elif check == "differs":
        marks.append("training data NOT as claimed")
    return marks
