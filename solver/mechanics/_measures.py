"""Scalar stress measures of a stress tensor field."""
from __future__ import annotations

import numpy as np


def von_mises(stress) -> np.ndarray:
    """Von Mises equivalent stress sqrt(3/2 s:s) of stresses (..., 3, 3), s the deviator."""
    s = np.asarray(stress, dtype=float)
    dev = s - np.trace(s, axis1=-2, axis2=-1)[..., None, None] * np.eye(3) / 3.0
    return np.sqrt(1.5 * np.einsum("...ij,...ij->...", dev, dev))
