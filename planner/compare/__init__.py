"""Comparison of predicted faces with post-operative scans (`faceplan compare`).

Superimposition of the scan on the unoperated regions by trimmed ICP (`alignment`), exact
signed point-to-surface distances (`distances`), area-weighted metrics overall and per region
(`metrics`), landmark errors with anatomical refinement (`landmarks`), the per-case pipeline
(`comparison`, `inputs`, `outputs`) and cohort tables (`cohort`). `phantom` is an analytic
face with regions and landmarks used by the tests and the benchmark.
"""
from planner.compare.alignment import Alignment, align_to_reference, trimmed_icp
from planner.compare.comparison import Comparison, compare_surfaces
from planner.compare.distances import TriangleSurface, vertex_areas
from planner.compare.inputs import Prediction, Surface, load_surface, read_inputs, read_prediction
from planner.compare.metrics import distance_metrics

__all__ = [
    "Alignment", "align_to_reference", "trimmed_icp", "Comparison", "compare_surfaces",
    "TriangleSurface", "vertex_areas", "Prediction", "Surface", "load_surface",
    "read_prediction", "read_inputs", "distance_metrics",
]
