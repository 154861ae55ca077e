"""The material protocol of the FE core and helpers shared by all hyperelastic laws.

Materials follow the uncoupled (Flory) split of the strain energy, W = W_iso(C_bar) + U(J),
with C_bar = J^(-2/3) C (Holzapfel, *Nonlinear Solid Mechanics*, 2000, sec. 6.4). A material
evaluates, vectorised over any leading shape (all quadrature points of all cells at once), the
isochoric second Piola-Kirchhoff stress S_iso = 2 dW_iso/dC, its material tangent
CC_iso = 4 d^2 W_iso / dC dC (so that dS = CC : dC / 2), the energy density, and the volumetric
function U(J) with its first two derivatives. Units: kPa (= mJ/mm^3), mm.

The helpers give the isochoric invariants I1_bar = J^(-2/3) tr C and I4_bar = J^(-2/3) a0.C.a0
with their first and second derivatives with respect to C, so that any invariant-based law
W_iso(I1_bar, I4_bar) is written as S = 2 sum(dW/dI dI/dC) and
CC = 4 sum(d2W/dI dJ dI/dC (x) dJ/dC + dW/dI d2I/dCdC).
"""
from __future__ import annotations

import math
from typing import Protocol, runtime_checkable

import numpy as np

from solver.errors import MaterialError

__all__ = [
    "Material",
    "check_parameters",
    "identity",
    "inverse_and_det",
    "i1_bar",
    "i4_bar",
    "outer",
    "sym_product",
]


@runtime_checkable
class Material(Protocol):
    """Uncoupled hyperelastic material, W = W_iso(C_bar) + U(J).

    `parameters` maps a name to (value, unit). `isochoric(C, fibres=None, load=1.0,
    tangent=True)` returns (S_iso (...,3,3), CC_iso (...,3,3,3,3), W_iso (...)) for right
    Cauchy-Green tensors C (...,3,3); `fibres` (...,3) are unit reference fibre directions or
    None; `load` in [0, 1] is the load fraction for ramped parts (active muscle stress);
    without `tangent` CC_iso is None (a residual or a stress needs no fourth-order tensor, whose
    81 components per point cost more than the rest). `volumetric(J)` returns
    (U, dU/dJ, d2U/dJ2), each shaped like J.
    """

    parameters: dict[str, tuple[float, str]]

    def isochoric(self, C, fibres=None, load=1.0, tangent=True): ...

    def volumetric(self, J): ...


def check_parameters(law: str, values: dict[str, float], rules: dict[str, str]) -> None:
    """Validate material parameters. `rules[name]` is one of '>0', '>=0', 'any'.

    Raises MaterialError naming the law and the parameter.
    """
    for name, rule in rules.items():
        if name not in values:
            raise MaterialError(f"{law}: parameter '{name}' is missing", parameter=name)
        v = values[name]
        try:
            v = float(v)
        except (TypeError, ValueError):
            raise MaterialError(f"{law}: parameter '{name}' must be a number, got {v!r}",
                                parameter=name) from None
        if not math.isfinite(v):
            raise MaterialError(f"{law}: parameter '{name}' must be finite, got {v}", parameter=name)
        if rule == ">0" and not v > 0:
            raise MaterialError(f"{law}: parameter '{name}' must be > 0, got {v}", parameter=name)
        if rule == ">=0" and not v >= 0:
            raise MaterialError(f"{law}: parameter '{name}' must be >= 0, got {v}", parameter=name)


def identity(shape=()) -> np.ndarray:
    """Identity tensors broadcast to shape (..., 3, 3)."""
    return np.broadcast_to(np.eye(3), tuple(shape) + (3, 3))


def inverse_and_det(C: np.ndarray):
    """Closed-form inverse and determinant of (..., 3, 3) matrices (faster than np.linalg)."""
    c = C
    cof = np.empty_like(c)
    cof[..., 0, 0] = c[..., 1, 1] * c[..., 2, 2] - c[..., 1, 2] * c[..., 2, 1]
    cof[..., 0, 1] = c[..., 1, 2] * c[..., 2, 0] - c[..., 1, 0] * c[..., 2, 2]
    cof[..., 0, 2] = c[..., 1, 0] * c[..., 2, 1] - c[..., 1, 1] * c[..., 2, 0]
    cof[..., 1, 0] = c[..., 0, 2] * c[..., 2, 1] - c[..., 0, 1] * c[..., 2, 2]
    cof[..., 1, 1] = c[..., 0, 0] * c[..., 2, 2] - c[..., 0, 2] * c[..., 2, 0]
    cof[..., 1, 2] = c[..., 0, 1] * c[..., 2, 0] - c[..., 0, 0] * c[..., 2, 1]
    cof[..., 2, 0] = c[..., 0, 1] * c[..., 1, 2] - c[..., 0, 2] * c[..., 1, 1]
    cof[..., 2, 1] = c[..., 0, 2] * c[..., 1, 0] - c[..., 0, 0] * c[..., 1, 2]
    cof[..., 2, 2] = c[..., 0, 0] * c[..., 1, 1] - c[..., 0, 1] * c[..., 1, 0]
    det = (c[..., 0, 0] * cof[..., 0, 0] + c[..., 0, 1] * cof[..., 0, 1]
           + c[..., 0, 2] * cof[..., 0, 2])
    inv = np.swapaxes(cof, -1, -2) / det[..., None, None]
    return inv, det


def outer(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """Dyadic product (A (x) B)_ijkl = A_ij B_kl."""
    return A[..., :, :, None, None] * B[..., None, None, :, :]


def sym_product(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """(A (.) B)_ijkl = (A_ik B_jl + A_il B_jk) / 2, e.g. -dC^-1/dC = C^-1 (.) C^-1."""
    return 0.5 * (A[..., :, None, :, None] * B[..., None, :, None, :]
                  + A[..., :, None, None, :] * B[..., None, :, :, None])


def i1_bar(C: np.ndarray, second: bool = True):
    """I1_bar = J^(-2/3) tr C and its derivatives with respect to C.

    Returns (I1b, dI1b (...,3,3), d2I1b (...,3,3,3,3) or None without `second`, Cinv, J) with
    dI1b = J^(-2/3) (I - I1/3 C^-1) and
    d2I1b = J^(-2/3) [ -1/3 (I (x) C^-1 + C^-1 (x) I) + I1/9 C^-1 (x) C^-1 + I1/3 C^-1 (.) C^-1 ].
    """
    Cinv, detC = inverse_and_det(C)
    J = np.sqrt(detC)
    a = detC ** (-1.0 / 3.0)
    I1 = np.trace(C, axis1=-2, axis2=-1)
    eye = identity(C.shape[:-2])
    I1b = a * I1
    dI1b = a[..., None, None] * (eye - (I1 / 3.0)[..., None, None] * Cinv)
    if not second:
        return I1b, dI1b, None, Cinv, J
    aa = a[..., None, None, None, None]
    d2 = aa * (-(outer(eye, Cinv) + outer(Cinv, eye)) / 3.0
               + (I1 / 9.0)[..., None, None, None, None] * outer(Cinv, Cinv)
               + (I1 / 3.0)[..., None, None, None, None] * sym_product(Cinv, Cinv))
    return I1b, dI1b, d2, Cinv, J


def i4_bar(C: np.ndarray, a0: np.ndarray, second: bool = True):
    """I4_bar = J^(-2/3) a0.C.a0 (squared isochoric fibre stretch) and its derivatives.

    a0 (...,3) unit reference fibre directions. Returns (I4b, dI4b, d2I4b or None without
    `second`) with
    dI4b = J^(-2/3) (a0 (x) a0 - I4/3 C^-1) and
    d2I4b = J^(-2/3) [ -1/3 (A0 (x) C^-1 + C^-1 (x) A0) + I4/9 C^-1 (x) C^-1 + I4/3 C^-1 (.) C^-1 ].
    """
    Cinv, detC = inverse_and_det(C)
    a = detC ** (-1.0 / 3.0)
    A0 = a0[..., :, None] * a0[..., None, :]
    I4 = np.einsum("...ij,...ij->...", C, A0)
    I4b = a * I4
    dI4b = a[..., None, None] * (A0 - (I4 / 3.0)[..., None, None] * Cinv)
    if not second:
        return I4b, dI4b, None
    aa = a[..., None, None, None, None]
    d2 = aa * (-(outer(A0, Cinv) + outer(Cinv, A0)) / 3.0
               + (I4 / 9.0)[..., None, None, None, None] * outer(Cinv, Cinv)
               + (I4 / 3.0)[..., None, None, None, None] * sym_product(Cinv, Cinv))
    return I4b, dI4b, d2
