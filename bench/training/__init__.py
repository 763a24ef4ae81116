"""Trained methods: the contract, checkpoints with identity, the one training driver and the
one training loop. The names below are the API a trained method imports; the modules:

    data.py         the training data (TrainOn, TrainSource, open_training_data)
    checkpoints.py  checkpoints with identity, in the cache and shipped (Checkpoint, ship)
    trained.py      the contract (TrainedMethod), the run handed to fit, the driver (train)
    claims.py       a manifest's claims checked: steps of planned, training data by content
    loop.py         the one training loop (fit_loop) and its generic pieces
    tokenized.py    a world model on a tokenizer's checkpoint (OnTokenizer): found, resumed on,
                    shipped without a second copy, loaded and checked

A method that learns subclasses :class:`TrainedMethod` and implements ``fit`` (train on a
:class:`TrainSource`, saving through the :class:`TrainingRun` it is handed, resuming from
what that run gives back) and ``load`` (take the weights of a verified :class:`Checkpoint`).
``pcfbench train METHOD[:opts] --dataset NAME[=ROOT]`` drives any of them (:func:`train`).
A ``fit`` that trains a torch model by gradient steps hands its model, optimiser, batch sampler
and step function to :func:`~pcfbench.training.loop.fit_loop` (re-exported here), which owns
seeding, resume, the random state, autocast, clipping, the schedule, timing, the saves and
the curve.

A checkpoint is a folder keyed by method, version, options hash and training data (dataset,
split, a hash of the dataset's file fingerprint and root options) under
``<cache>/checkpoints``::

    manifest.json            what it is: method, version, options, train_on, the training
                             files' content hashes, steps (and planned), wall and CPU time,
                             device, git commit, the sha256 of each file below
    weights-<step>.pt        the model's tensors (loads with torch.load(weights_only=True))
    state-<step>.pt          optimiser and RNG state to resume from (weights_only too)

The manifest is replaced atomically after both files it names are written, so a run killed
at any moment (SIGKILL included) leaves a consistent checkpoint: the last one saved.
:meth:`Checkpoint.open` refuses a checkpoint whose files do not match their sha256
(truncated, tampered) and :meth:`Checkpoint.check_method` one made by another method,
version or option set: one error naming the file either way.

Shipped checkpoints travel inside a method's package (package data), in
``<package>/checkpoints/<method>/v<version>/<options hash>/<dataset>.<split>/``: the
manifest of the trained checkpoint (weights in float16, no optimiser state) plus a
``shipped`` record (the cache checkpoint's sha256, the training data's content sha256, for
a dataset that makes its own data the sha256 of its recipe, the retrain command).
:func:`checkpoint_for` takes one when the cache holds none trained on that dataset and split:
at once when the dataset, at its default root, is made by the very recipe recorded
(:func:`find_shipped_by_recipe`; the training data is then never made here), else when the
local training data has the same content (:func:`find_checkpoint`). It is verified and loaded
like any checkpoint (float16 tensors cast back to float32). :func:`ship` writes one.
"""

from pcfbench.training.checkpoints import (Checkpoint, CheckpointError, checkpoint_dir, checkpoint_for,
                                           checkpoint_options_hash, find_checkpoint, find_shipped,
                                           find_shipped_by_recipe, missing_checkpoint_message, retrain_command, ship,
                                           shipped_dir)
from pcfbench.training.data import TrainOn, TrainSource, data_recipe_sha256, open_training_data, recipe_sha256
from pcfbench.training.loop import (LoopResult, Panel, Randoms, StateError, adamw, autocast, default_device, fit_loop,
                                    param_groups, synchronize, warmup_cosine, write_curve)
from pcfbench.training.trained import TrainedMethod, TrainingInterrupted, TrainingRun, is_trained, train

__all__ = [
    "Checkpoint", "CheckpointError", "TrainOn", "TrainSource", "TrainedMethod", "TrainingInterrupted", "TrainingRun",
    "checkpoint_dir",
    "checkpoint_for", "checkpoint_options_hash", "data_recipe_sha256", "find_checkpoint", "find_shipped",
    "find_shipped_by_recipe", "is_trained", "missing_checkpoint_message", "open_training_data", "recipe_sha256",
    "retrain_command", "ship", "shipped_dir", "train",
    # the one training loop (pcfbench.training.loop)
    "LoopResult", "Panel", "Randoms", "StateError", "adamw", "autocast", "default_device", "fit_loop", "param_groups",
    "synchronize", "warmup_cosine", "write_curve",
]
