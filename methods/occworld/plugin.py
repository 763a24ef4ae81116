"""OccWorld as a plugin (the ``builtin-occworld`` entry point): the tokenizer as the trained
method ``occworld-occ-copy`` (the last past occupancy's tokens, decoded and rendered at every
future pose) and the world model ``occworld`` on top of its checkpoint. Neither ships a
checkpoint yet, so the default run leaves them out (docs/occworld.md)."""

from __future__ import annotations

from pcfbench.hookspecs import hookimpl


@hookimpl
def register_methods(register):  # noqa: ANN001
    register("occworld-occ-copy", "pcfbench.methods.occworld.occ_copy:OccCopy",
             "OccWorld's occupancy tokenizer decoding the t=0 occupancy's tokens from every future pose (trained)")
    register("occworld", "pcfbench.methods.occworld.forecaster:OccWorld",
             "OccWorld: occupancy tokenizer + spatio-temporal generative transformer, autoregressive (trained)")
