"""Metrics: small named, versioned functions of one future sweep (docs/protocol.md section 4)."""

from pcfbench.metrics.base import Metric, SweepContext, score_sample

__all__ = ["Metric", "SweepContext", "score_sample"]
