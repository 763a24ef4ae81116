"""Built-in metrics, registered through the same hook as third-party ones."""

from bench.hookspecs import hookimpl


@hookimpl
def register_metrics(register):
    register("chamfer", "bench.metrics.chamfer:CHAMFER", "Chamfer distance, uncropped")
    register("chamfer_nf", "bench.metrics.chamfer:CHAMFER_NF", "near-field Chamfer (ROI crop)")
