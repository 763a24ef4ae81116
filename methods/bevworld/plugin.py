"""BEVWorld as a plugin (the ``builtin-bevworld`` entry point): the tokenizer as the trained
method ``bevworld-latent-copy`` (the last past sweep's latent, decoded and rendered at every
future pose) and the world model ``bevworld`` on top of its checkpoint. Neither ships a
checkpoint yet; the default run leaves them out (docs/bevworld.md)."""

from __future__ import annotations

from pcfbench.hookspecs import hookimpl


@hookimpl
def register_methods(register):  # noqa: ANN001
    register("bevworld-latent-copy", "pcfbench.methods.bevworld.latent_copy:LatentCopy",
             "BEVWorld's LiDAR tokenizer rendering the t=0 sweep's continuous BEV latent from every future pose "
             "(trained)")
    register("bevworld", "pcfbench.methods.bevworld.forecaster:BevWorld",
             "BEVWorld: continuous BEV latent tokenizer + latent diffusion transformer, DDIM (trained)")
