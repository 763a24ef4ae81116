"""What the three forecasting Copilot4D methods (``copilot4d-token-copy``, ``copilot4d``,
``copilot4d-maskgit``) share in their options: how a token map is rendered into depths
(``evaluate.render_codes``). Light on purpose: options are built without importing torch."""

from __future__ import annotations

from dataclasses import dataclass

from pcfbench.options import option

#: how ``render_codes`` turns a ray's weights into a depth
READOUTS = ("expected", "median")


def check_readout(readout: str) -> None:
    """One error for a ``readout`` that ``render_codes`` does not know."""
    from pcfbench.errors import PcfbenchError

    if readout not in READOUTS:
        raise PcfbenchError(f"readout={readout!r}: expected one of {', '.join(READOUTS)}")


@dataclass(frozen=True)
class RenderingOptions:
    """Inference-only: they change how a checkpoint's tokens are rendered, never its weights."""

    threshold: float = option(0.02, help="spatial skipping: coarse-voxel probability threshold when rendering "
                                         "(the paper gives none)", gt=0, lt=1)
    noise: bool = option(False, help="spatial skipping: Logistic noise on the coarse logits (figure 8)")
    readout: str = option("median", help="a ray's depth from its weights: median (where half of the weight "
                                         "is reached) or expected (equation 4)")

    def __post_init__(self) -> None:
        check_readout(self.readout)
