"""The generic structured hexahedral face mesh: builder (`generic_mesh.builder`) and the
built meshes committed under `generic_mesh/data/face_<resolution>.vtu` (+ JSON sidecar).

`load(resolution)` returns the committed `facemodel.FaceModel`; `python -m generic_mesh`
rebuilds the files and prints element counts and quality per resolution.
"""
from __future__ import annotations

from functools import lru_cache
from pathlib import Path

DATA = Path(__file__).parent / "data"
RESOLUTIONS = ("coarse", "standard", "fine")

__all__ = ["load", "path_of", "mean_head", "RESOLUTIONS", "DATA"]


def path_of(resolution: str) -> Path:
    if resolution not in RESOLUTIONS:
        raise ValueError(f"resolution must be one of {', '.join(RESOLUTIONS)}, got {resolution!r}")
    return DATA / f"face_{resolution}.vtu"


@lru_cache(maxsize=3)
def _load(resolution: str):
    from facemodel.model import FaceModel

    path = path_of(resolution)
    if not path.exists():
        from generic_mesh.builder import build

        model = build(resolution)
        try:
            model.save(path)
        except OSError:
            pass
        return model
    return FaceModel.load(path)


def load(resolution: str = "standard"):
    """The generic FaceModel at `resolution` ('coarse' <= 2,000 hexahedra, 'standard'
    8,000-15,000, 'fine' >= 40,000). The model is immutable and shared between calls."""
    return _load(resolution)


@lru_cache(maxsize=2)
def mean_head(size: float = 2.0):
    """The closed surfaces of the mean head the generic mesh was built in (same geometry,
    same frame): `facemodel.synthetic.SyntheticHead` with the generic shape (skin, bone
    segments skull/maxilla/mandible/chin, teeth, landmarks), e.g. to register the generic
    bones onto a patient's."""
    from facemodel import head_geometry as hg
    from facemodel import synthetic as sy

    shape = hg.GENERIC
    teeth = {"upper": (*hg.teeth_arch("upper", shape), "maxilla"),
             "lower": (*hg.teeth_arch("lower", shape), "mandible")}
    return sy.SyntheticHead(seed=-1, shape=shape, skin=sy.skin_surface(shape, size),
                            bones=sy.bone_surfaces(shape), teeth=teeth, landmarks=sy.landmarks(shape))
