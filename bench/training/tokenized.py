"""A trained method that learns on the outputs of another trained method's network: a world
model on its tokenizer's tokens or latents (``occworld`` on ``occworld-occ-copy``, ``bevworld``
on ``bevworld-latent-copy``).

Its checkpoint holds the tokenizer it trained with (weights under ``tokenizer.``, their
:func:`tensor_digest` in the manifest's ``config.tokenizer_digest``), so a cached checkpoint
stands alone. :class:`OnTokenizer` gives such a method what every one of them needs:

- ``tokenizer_checkpoint``: the tokenizer's checkpoint for the training data (missing: one
  error saying how to train it), and ``check_resumed_tokenizer``: a resumed training refuses a
  tokenizer checkpoint other than the one it started on;
- ``shipped_weights``: shipped, the world model leaves out its copy of the tokenizer when the
  tokenizer's own shipped checkpoint for the same data holds the very same one (the digest, which
  float16 rounding does not change), recording where it is (``shipped.left_out``);
- ``checkpoint_tokenizer``: the tokenizer of a checkpoint, from its own tensors or, shipped
  without them, from that shipped checkpoint (checked by its sha256), then checked against the
  digest either way.

:func:`load_network` puts a checkpoint's tensors under a prefix into a network (float16 ones
as float32), one error naming the file when they do not fit it.
"""

from __future__ import annotations

import hashlib
import json
from abc import abstractmethod
from pathlib import Path
from typing import TYPE_CHECKING, Any, ClassVar

from pcfbench.training.checkpoints import (MANIFEST, Checkpoint, CheckpointError, find_checkpoint,
                                          missing_checkpoint_message, shipped_dir)

if TYPE_CHECKING:
    from pcfbench.method import MethodSpec
    from pcfbench.training.data import TrainSource

#: the prefix of the tokenizer's tensors in a world model's checkpoint
TOKENIZER_PREFIX = "tokenizer."


def tensor_digest(state: dict) -> str:
    """sha256 over the names, shapes and values of a state dict's tensors, floating-point ones
    rounded to float16 (so the fp16 copy of float32 weights has the digest of the original)."""
    h = hashlib.sha256()
    for k in sorted(state):
        t = state[k].detach().cpu()
        if t.is_floating_point():
            t = t.half().float()
        h.update(f"{k}|{tuple(t.shape)}|{t.dtype}|".encode())
        h.update(t.contiguous().numpy().tobytes())
    return h.hexdigest()


def load_network(network, checkpoint: Checkpoint, weights: dict, prefix: str, what: str):
    """``network`` with ``weights``' tensors under ``prefix`` (the prefix dropped; floating-point
    ones as float32); ``what`` names the network in the error when they do not fit it."""
    state = {k[len(prefix):]: (v.float() if v.is_floating_point() else v)
             for k, v in weights.items() if k.startswith(prefix)}
    try:
        network.load_state_dict(state)
    except RuntimeError as exc:
        raise CheckpointError(f"checkpoint {checkpoint.weights_path}: its {what} weights do not fit the network it "
                              f"records: {str(exc).splitlines()[0]}") from None
    return network


class OnTokenizer:
    """Mixin of a :class:`~pcfbench.training.TrainedMethod` whose world model learns on a
    tokenizer's outputs (module docstring). The method defines ``tokenizer_spec`` (the tokenizer
    method and options its own options name), ``read_tokenizer`` (the tokenizer network of a
    checkpoint of that method, or of this one under ``prefix``) and ``world_cfg`` (its world
    model's configuration, which has a ``name``)."""

    #: what the world model learns on, for messages: "tokens", "latents"
    tokenizer_outputs: ClassVar[str] = "tokens"
    name: ClassVar[str]

    @abstractmethod  # with TrainedMethod (an ABC), a class that lacks one cannot be instantiated
    def tokenizer_spec(self) -> MethodSpec:
        """The tokenizer method and options this method's options name."""

    @abstractmethod
    def read_tokenizer(self, checkpoint: Checkpoint, prefix: str = "", weights: dict | None = None) -> Any:
        """The tokenizer network of ``checkpoint`` (its tensors under ``prefix``; ``weights``: the
        checkpoint's tensors when already read)."""

    def tokenizer_checkpoint(self, train_source: TrainSource) -> Checkpoint:
        spec = self.tokenizer_spec()
        ck = find_checkpoint(spec, train_source.train_on)
        if ck is None:
            raise CheckpointError(f"{self.name} trains on the {self.tokenizer_outputs} of its tokenizer: "
                                  + missing_checkpoint_message(spec, train_source.train_on))
        return ck

    def check_resumed_tokenizer(self, out_dir: Path, tokenizer: Checkpoint) -> None:
        """A training resumed in ``out_dir`` goes on only on the tokenizer checkpoint it started on."""
        manifest = Path(out_dir) / MANIFEST
        had = json.loads(manifest.read_text())["config"].get("tokenizer_sha256")
        if had != tokenizer.sha256:
            raise CheckpointError(f"checkpoint {manifest} was trained on the {self.tokenizer_outputs} of tokenizer "
                                  f"{str(had)[:12]}, and {tokenizer.manifest_path} is now {tokenizer.sha256[:12]}: "
                                  "rerun with --fresh")

    def shipped_tokenizer(self, checkpoint: Checkpoint) -> Checkpoint | None:
        """The tokenizer's checkpoint shipped for the data ``checkpoint`` was trained on (verified
        by its own sha256), or None when none ships."""
        folder = shipped_dir(self.tokenizer_spec(), checkpoint.train_on["dataset"], checkpoint.train_on["split"])
        return Checkpoint.open(folder) if folder is not None and (folder / MANIFEST).is_file() else None

    def shipped_weights(self, checkpoint: Checkpoint, weights: dict) -> tuple[dict, dict | None]:
        """The world model's tensors alone when its tokenizer ships holding the very tokenizer it
        trained with: the copy would double the package's checkpoints."""
        tok_ck = self.shipped_tokenizer(checkpoint)
        if (tok_ck is None or tensor_digest(self.read_tokenizer(tok_ck).state_dict())
                != checkpoint.manifest.get("config", {}).get("tokenizer_digest")):
            return weights, None
        return ({k: v for k, v in weights.items() if not k.startswith(TOKENIZER_PREFIX)},
                {"prefix": TOKENIZER_PREFIX, "method": self.tokenizer_spec().name, "weights_sha256": tok_ck.sha256})

    def load_world(self, checkpoint: Checkpoint, network, config_from_dict) -> tuple[Any, Any]:
        """(tokenizer, ``network``) of ``checkpoint``: its manifest must record the world model's
        configuration (read by ``config_from_dict``) equal to ``self.world_cfg``, the tokenizer's
        and its digest; the network takes the tensors under ``world.``."""
        mf = checkpoint.manifest_path
        conf = checkpoint.manifest.get("config", {})
        for key in ("world", "tokenizer", "tokenizer_digest"):
            if key not in conf:
                raise CheckpointError(f"checkpoint {mf} records no config.{key}: not a checkpoint of {self.name}")
        if config_from_dict(conf["world"]) != self.world_cfg:
            raise CheckpointError(f"checkpoint {mf} was trained with another '{self.world_cfg.name}' world model "
                                  "configuration than this pcfbench defines; retrain it with --fresh")
        weights = checkpoint.load_weights()
        tokenizer = self.checkpoint_tokenizer(checkpoint, weights)
        return tokenizer, load_network(network, checkpoint, weights, "world.", "world model")

    def checkpoint_tokenizer(self, checkpoint: Checkpoint, weights: dict):
        """The tokenizer ``checkpoint`` (with its ``weights`` read) was trained with."""
        mf = checkpoint.manifest_path
        left_out = (checkpoint.manifest.get("shipped") or {}).get("left_out")
        if any(k.startswith(TOKENIZER_PREFIX) for k in weights):
            tokenizer = self.read_tokenizer(checkpoint, TOKENIZER_PREFIX, weights)
        elif left_out:  # shipped without it: the tokenizer's own shipped checkpoint holds it
            tok_ck = self.shipped_tokenizer(checkpoint)
            if tok_ck is None or tok_ck.sha256 != left_out.get("weights_sha256"):
                raise CheckpointError(f"checkpoint {mf} ships without its tokenizer, which the "
                                      f"{self.tokenizer_spec().name} checkpoint shipped for "
                                      f"{checkpoint.train_on_label} (weights sha256 "
                                      f"{str(left_out.get('weights_sha256'))[:12]}) holds, and that one is "
                                      f"{'missing' if tok_ck is None else 'another: ' + tok_ck.sha256[:12]}; "
                                      "reinstall pcfbench or retrain both")
            tokenizer = self.read_tokenizer(tok_ck)
        else:
            raise CheckpointError(f"checkpoint {checkpoint.weights_path} holds no tokenizer weights: not a "
                                  f"checkpoint of {self.name}")
        if tensor_digest(tokenizer.state_dict()) != checkpoint.manifest.get("config", {}).get("tokenizer_digest"):
            raise CheckpointError(f"checkpoint {checkpoint.weights_path}: its tokenizer weights are not the tokenizer "
                                  f"it was trained with (the manifest {mf} records another digest); retrain with --fresh")
        return tokenizer
