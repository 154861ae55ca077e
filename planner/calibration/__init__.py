"""Patient-specific tissue parameters from in-vivo aspiration and indentation (`faceplan calibrate`).

`slab` holds the forward FE models (a layered wedge slab under an aspiration aperture or a rigid
sphere), `data` reads and checks the measurements, `emulator` the Gaussian-process emulator and
the dask forward runs, `identify` the least-squares estimate, the posterior and the Sobol table,
`run` the workflow, `outputs` the pictures and files, `materials` the hand-over to `predict`.
"""
from planner.calibration.data import SiteData, read_calibration_data
from planner.calibration.materials import read_materials, with_materials
from planner.calibration.slab import MeshOptions, Site, forward_curve

__all__ = ["SiteData", "read_calibration_data", "read_materials", "with_materials",
           "MeshOptions", "Site", "forward_curve"]
