"""Rigid transforms from ITK text transform files, as 3D Slicer saves them.

An ITK transform file (`#Insight Transform File V1.0`, usually `.tfm` or `.txt`) stores a
transform in ITK's *resampling* convention and in ITK's LPS world frame: it maps points of the
fixed (output) space to the moving (input) space. 3D Slicer shows and applies linear transforms
in the *modelling* convention (the "to parent" transform that moves a model) in RAS, and when it
saves one it writes the inverse, converted to LPS (Slicer developer guide, "Transforms":
"transform files"). The movement of a bone segment in RAS is therefore

    M_RAS = F · inverse(T_LPS) · F,    F = diag(-1, -1, 1, 1)

which is what `read_itk_transform` returns. Supported classes (double or float):
`AffineTransform`, `MatrixOffsetTransformBase`, `Rigid3DTransform` (12 parameters: the 3x3 matrix
row by row then the translation), `Euler3DTransform` (angles about x, y, z in radians then the
translation; ITK composes R = Rz·Rx·Ry, or Rz·Ry·Rx when the fourth fixed parameter
ComputeZYX is 1), `VersorRigid3DTransform` (versor = vector part of a unit quaternion, then the
translation), `TranslationTransform`, and a `CompositeTransform` holding one of these. Every ITK
matrix-offset transform maps x -> A (x - c) + c + t with c the FixedParameters centre.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from planner.errors import InputError

LPS_FROM_RAS = np.diag([-1.0, -1.0, 1.0, 1.0])

_MATRIX_CLASSES = ("AffineTransform", "MatrixOffsetTransformBase", "Rigid3DTransform",
                   "ScalableAffineTransform")


def ras_from_lps(matrix_lps: np.ndarray) -> np.ndarray:
    """Express a 4x4 transform given in LPS in RAS (the change of basis is its own inverse)."""
    return LPS_FROM_RAS @ matrix_lps @ LPS_FROM_RAS


def _homogeneous(a: np.ndarray, t: np.ndarray, centre: np.ndarray) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3] = a
    m[:3, 3] = t + centre - a @ centre
    return m


def _rotation_x(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def _rotation_y(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def _rotation_z(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def _parse_blocks(text: str, file: str) -> list[dict[str, str]]:
    lines = [ln.strip() for ln in text.splitlines() if ln.strip()]
    if not lines or not lines[0].startswith("#Insight Transform File"):
        raise InputError("not an ITK text transform file (first line must be "
                         "'#Insight Transform File V1.0')", file=file)
    blocks: list[dict[str, str]] = []
    for ln in lines[1:]:
        if ln.startswith("#"):
            if ln.lower().startswith("#transform"):
                blocks.append({})
            continue
        if ":" not in ln:
            raise InputError(f"cannot read line {ln!r}", file=file)
        key, value = ln.split(":", 1)
        if not blocks:
            blocks.append({})
        blocks[-1][key.strip()] = value.strip()
    return [b for b in blocks if b]


def _numbers(block: dict[str, str], key: str, file: str, n: int | tuple[int, ...]) -> np.ndarray:
    if key not in block:
        if key == "FixedParameters":
            return np.zeros(3)
        raise InputError(f"missing {key}", file=file, field=key)
    try:
        values = np.array([float(v) for v in block[key].split()], dtype=float)
    except ValueError:
        raise InputError(f"{key} must be numbers, got {block[key]!r}", file=file, field=key) from None
    allowed = (n,) if isinstance(n, int) else n
    if values.size not in allowed:
        raise InputError(f"{key} must have {' or '.join(map(str, allowed))} values, got {values.size}",
                         file=file, field=key)
    if not np.all(np.isfinite(values)):
        raise InputError(f"{key} contains NaN or infinity", file=file, field=key)
    return values


def _block_matrix(block: dict[str, str], file: str) -> np.ndarray:
    """The 4x4 (resampling, LPS) matrix of one transform block."""
    kind = block.get("Transform", "")
    base = kind.split("_")[0]
    if not kind.endswith(("_double_3_3", "_float_3_3", "_double_3", "_float_3")):
        raise InputError(f"unsupported transform {kind!r}: only 3D linear transforms are accepted",
                         file=file, field="Transform")
    if base == "TranslationTransform":
        p = _numbers(block, "Parameters", file, 3)
        return _homogeneous(np.eye(3), p, np.zeros(3))
    fixed = _numbers(block, "FixedParameters", file, (3, 4))
    centre = fixed[:3]
    if base in _MATRIX_CLASSES:
        p = _numbers(block, "Parameters", file, 12)
        return _homogeneous(p[:9].reshape(3, 3), p[9:], centre)
    if base == "Euler3DTransform":
        p = _numbers(block, "Parameters", file, 6)
        rx, ry, rz = _rotation_x(p[0]), _rotation_y(p[1]), _rotation_z(p[2])
        compute_zyx = fixed.size == 4 and fixed[3] != 0
        a = rz @ ry @ rx if compute_zyx else rz @ rx @ ry
        return _homogeneous(a, p[3:], centre)
    if base == "VersorRigid3DTransform":
        p = _numbers(block, "Parameters", file, 6)
        v = p[:3]
        norm2 = float(v @ v)
        if norm2 > 1.0 + 1e-12:
            raise InputError("versor vector part has norm > 1", file=file, field="Parameters")
        w = np.sqrt(max(0.0, 1.0 - norm2))
        x, y, z = v
        a = np.array([
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ])
        return _homogeneous(a, p[3:], centre)
    raise InputError(f"unsupported transform {kind!r}: use an affine, Euler3D, VersorRigid3D or "
                     "translation transform", file=file, field="Transform")


def parse_itk_transform(text: str, file: str = "<transform>") -> np.ndarray:
    """The modelling (to-parent) 4x4 transform in RAS stored in ITK transform file text."""
    blocks = _parse_blocks(text, file)
    if blocks and blocks[0].get("Transform", "").startswith("CompositeTransform"):
        blocks = blocks[1:]
    if len(blocks) != 1:
        raise InputError(f"expected exactly one linear transform, found {len(blocks)}", file=file)
    resampling_lps = _block_matrix(blocks[0], file)
    if abs(np.linalg.det(resampling_lps[:3, :3])) < 1e-12:
        raise InputError("transform matrix is singular", file=file, field="Parameters")
    return ras_from_lps(np.linalg.inv(resampling_lps))


def read_itk_transform(path: str | Path) -> np.ndarray:
    """Read an ITK text transform file as 3D Slicer saves it; return the RAS movement (4x4)."""
    path = Path(path)
    if not path.is_file():
        raise InputError("transform file not found", file=str(path))
    try:
        text = path.read_text(encoding="utf-8")
    except (UnicodeDecodeError, OSError) as exc:
        raise InputError(f"cannot read as an ITK text transform ({exc.__class__.__name__}); "
                         "save it from Slicer as .tfm/.txt, not .h5/.mat", file=str(path)) from None
    return parse_itk_transform(text, str(path))


def format_itk_transform(movement_ras: np.ndarray) -> str:
    """ITK text file for a RAS movement, written as 3D Slicer writes it (inverse, LPS, affine)."""
    resampling_lps = LPS_FROM_RAS @ np.linalg.inv(movement_ras) @ LPS_FROM_RAS
    params = list(resampling_lps[:3, :3].ravel()) + list(resampling_lps[:3, 3])
    return ("#Insight Transform File V1.0\n"
            "#Transform 0\n"
            "Transform: AffineTransform_double_3_3\n"
            f"Parameters: {' '.join(repr(float(p)) for p in params)}\n"
            "FixedParameters: 0 0 0\n")
