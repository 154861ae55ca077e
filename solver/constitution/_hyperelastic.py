"""Isotropic uncoupled hyperelastic laws: neo-Hookean and Yeoh, with a volumetric penalty.

W_iso = sum_k C_k0 (I1_bar - 3)^k (Yeoh 1993, "Some forms of the strain energy function for
rubber"; neo-Hookean is the k = 1 case with C10 = mu/2), and
U(J) = K/2 (J^2 - 1)/2 - K/2 ln J (Simo-Taylor 1982 / FEBio "uncoupled" default form:
U' = K/2 (J - 1/J), U'' = K/2 (1 + 1/J^2)) or U = K/2 (J - 1)^2 on request. K is the
small-strain bulk modulus. Stress and tangent come from the I1_bar derivatives of
`solver.constitution.base`. Units: kPa.
"""
from __future__ import annotations

import numpy as np

from solver.constitution.base import check_parameters, i1_bar, outer

__all__ = ["Yeoh", "NeoHooke", "volumetric_function"]

_VOLUMETRIC = ("simo_taylor", "quadratic")


def volumetric_function(kind: str, K: float, J: np.ndarray):
    """U(J), U'(J), U''(J) for the named volumetric penalty with bulk modulus K."""
    J = np.asarray(J, dtype=float)
    if kind == "simo_taylor":
        U = 0.25 * K * (J * J - 1.0 - 2.0 * np.log(J))
        dU = 0.5 * K * (J - 1.0 / J)
        d2U = 0.5 * K * (1.0 + 1.0 / (J * J))
    elif kind == "quadratic":
        U = 0.5 * K * (J - 1.0) ** 2
        dU = K * (J - 1.0)
        d2U = np.full_like(J, K)
    else:
        raise ValueError(f"unknown volumetric function {kind!r}; use one of {_VOLUMETRIC}")
    return U, dU, d2U


class Yeoh:
    """Yeoh material: W_iso = C10 (I1b-3) + C20 (I1b-3)^2 + C30 (I1b-3)^3, U(J) with bulk K.

    Requires C10 > 0 and K > 0; C20, C30 may be negative (as in the benchmark set
    C = (0.5, -0.1, 0.02) kPa) but the initial shear modulus 2 C10 must be positive.
    """

    law = "Yeoh"

    def __init__(self, C10: float, C20: float = 0.0, C30: float = 0.0, K: float = None,
                 volumetric: str = "simo_taylor"):
        check_parameters(self.law, {"C10": C10, "C20": C20, "C30": C30, "K": K},
                         {"C10": ">0", "C20": "any", "C30": "any", "K": ">0"})
        if volumetric not in _VOLUMETRIC:
            from solver.errors import MaterialError
            raise MaterialError(f"{self.law}: volumetric must be one of {_VOLUMETRIC}, "
                                f"got {volumetric!r}", parameter="volumetric")
        self.C10, self.C20, self.C30, self.K = float(C10), float(C20), float(C30), float(K)
        self.volumetric_kind = volumetric
        self.parameters = {"C10": (self.C10, "kPa"), "C20": (self.C20, "kPa"),
                           "C30": (self.C30, "kPa"), "K": (self.K, "kPa")}

    def __repr__(self):
        p = ", ".join(f"{k}={v[0]:g}" for k, v in self.parameters.items())
        return f"{type(self).__name__}({p})"

    @property
    def shear_modulus(self) -> float:
        """Initial (small strain) shear modulus mu = 2 C10."""
        return 2.0 * self.C10

    def dW(self, I1b):
        """dW/dI1b and d2W/dI1b^2."""
        t = I1b - 3.0
        W = self.C10 * t + self.C20 * t * t + self.C30 * t ** 3
        W1 = self.C10 + 2.0 * self.C20 * t + 3.0 * self.C30 * t * t
        W11 = 2.0 * self.C20 + 6.0 * self.C30 * t
        return W, W1, W11

    def isochoric(self, C, fibres=None, load=1.0, tangent=True):
        C = np.asarray(C, dtype=float)
        I1b, dI, d2I, _, _ = i1_bar(C, second=tangent)
        W, W1, W11 = self.dW(I1b)
        S = 2.0 * W1[..., None, None] * dI
        if not tangent:
            return S, None, W
        CC = 4.0 * (W11[..., None, None, None, None] * outer(dI, dI)
                    + W1[..., None, None, None, None] * d2I)
        return S, CC, W

    def volumetric(self, J):
        return volumetric_function(self.volumetric_kind, self.K, J)


class NeoHooke(Yeoh):
    """Uncoupled neo-Hookean material, W_iso = mu/2 (I1b - 3), U(J) with bulk modulus K."""

    law = "neo-Hookean"

    def __init__(self, mu: float, K: float, volumetric: str = "simo_taylor"):
        check_parameters(self.law, {"mu": mu, "K": K}, {"mu": ">0", "K": ">0"})
        super().__init__(C10=0.5 * float(mu), K=K, volumetric=volumetric)
        self.mu = float(mu)
        self.parameters = {"mu": (self.mu, "kPa"), "K": (self.K, "kPa")}
