"""Built-in metrics, registered through the same hook as third-party ones."""

from pcfbench.hookspecs import hookimpl


@hookimpl
def register_metrics(register):
    register("chamfer", "pcfbench.metrics.chamfer:CHAMFER", "Chamfer distance, uncropped")
    register("chamfer_nf", "pcfbench.metrics.chamfer:CHAMFER_NF", "near-field Chamfer (ROI crop)")
    register("chamfer_nf@4docc", "pcfbench.metrics.chamfer:CHAMFER_NF_4DOCC", "near-field Chamfer, empty crop = 0")
    register("l1@4docc", "pcfbench.metrics.depth:L1_4DOCC", "L1 depth error, 4D-Occ angle space and denominator")
    register("absrel@4docc", "pcfbench.metrics.depth:ABSREL_4DOCC", "AbsRel, 4D-Occ angle space and denominator")
    register("l1_mean", "pcfbench.metrics.depth:L1_MEAN", "L1 depth error, mean over kept rays")
    register("absrel_mean", "pcfbench.metrics.depth:ABSREL_MEAN", "AbsRel, mean over kept rays")
    register("l1_median", "pcfbench.metrics.depth:L1_MEDIAN", "L1 depth error, median over kept rays")
    register("absrel_median", "pcfbench.metrics.depth:ABSREL_MEDIAN", "AbsRel, median over kept rays")
    register("l1_ray", "pcfbench.metrics.depth:L1_RAY", "ray-query mode L1 (per-ray depths)")
    register("absrel_ray", "pcfbench.metrics.depth:ABSREL_RAY", "ray-query mode AbsRel (per-ray depths)")
