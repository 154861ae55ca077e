"""Active transversely isotropic muscle: Yeoh matrix, passive fibres, active fibre stress.

Uncoupled strain energy W = W_iso(I1_bar, I4_bar; a) + U(J) (Weiss, Maker & Govindjee 1996;
Blemker, Pinsky & Delp 2005) with four isochoric parts:

* matrix (Yeoh 1993): sum_k C_k0 (I1b - 3)^k;
* passive fibres, stiffening in isochoric fibre stretch lam = sqrt(I4b) > 1 only
  (exponential form of Holzapfel, Gasser & Ogden 2000): k1/(2 k2) (exp(k2 (I4b - 1)^2) - 1);
* active fibre stress, defined through dW_a/dlam = a T_max f(lam) / lam_opt: the force-length
  relation is one of force, so it is the nominal (first Piola-Kirchhoff) fibre stress that
  follows it, and the Cauchy stress gains a T_max f(lam) lam/lam_opt m (x) m (m the current fibre
  direction, up to the pressure that the uncoupled split adds; Blemker, Pinsky & Delp 2005,
  eqs. 13-14; FEBio's muscle material). The force-length relation is the log-Gaussian
  f(lam) = exp(-(ln(lam/lam_opt)/w)^2) (Otten 1987 form; width w), whose energy is closed form
  (u = ln(lam/lam_opt), substituting lam = lam_opt e^u):
  W_a = a T_max e^(w^2/4) w sqrt(pi)/2 [erf(u/w - w/2) - erf(u(1)/w - w/2)].
  With an active Cauchy stress a T f(lam) instead, the nominal fibre stress a T f/lam falls
  with stretch at lam_opt (slope -a T / lam_opt^2): once a T_max exceeds the matrix's
  along-fibre stiffness (3 mu at small strain) the along-fibre tangent turns negative and a
  muscle at rest length collapses onto itself (a material instability, not a property of
  muscle). Here the active part adds no stiffness at lam_opt, stiffness on the ascending limb
  (lam < lam_opt) and softening only on the descending one;
* lateral (cross-fibre) stiffness that grows with activation, the role of the extra isochoric
  term of the seed's "Usermat" muscle law (Nazari et al. 2010, Payan & Perrier 2016:
  activated muscle is stiffer across its fibres): mu_T(a)/2 (I1b - I4b - 2/sqrt(I4b)) with
  mu_T(a) = G_T + a G_T_active. The bracket is >= 0 and vanishes exactly when the cross-fibre
  plane deforms by a pure in-plane dilatation without along-fibre shear (det C_bar = 1 gives
  tr of the transverse block >= 2/sqrt(I4b)); it adds no stiffness in pure fibre stretch.

The activation a in [0, 1] is ramped with the solver's load fraction: a(load) = a * load.
Stress S = 2 sum W_i dI_i/dC and tangent CC = 4 sum (W_ij dI_i (x) dI_j + W_i d2I_i) use the
I1_bar/I4_bar derivatives of `solver.constitution.base`; the volumetric part U(J) is the
solver's volumetric function (the Q1/P0 mean dilatation is applied by the element).
Units: kPa, mm.
"""
from __future__ import annotations

import math

import numpy as np
from scipy.special import erf

from solver.constitution.base import check_parameters, i1_bar, i4_bar, outer
from solver.constitution._hyperelastic import _VOLUMETRIC, volumetric_function
from solver.errors import MaterialError

__all__ = ["Muscle", "force_length"]

# Above this value of k2 (I4b - 1)^2 the exponential is frozen at its value (the stretch is far
# beyond anything physiological; it only keeps a failed Newton iterate from overflowing).
_EXP_CAP = 60.0


def force_length(lam, lam_opt: float = 1.0, width: float = 0.5):
    """Active force-length relation f(lam) = exp(-(ln(lam/lam_opt)/width)^2), f(lam_opt) = 1."""
    u = np.log(np.asarray(lam, dtype=float) / lam_opt) / width
    return np.exp(-u * u)


class Muscle:
    """Active transversely isotropic muscle (see module docstring for the energy).

    Parameters (kPa unless stated): Yeoh matrix C10 > 0, C20, C30; bulk modulus K > 0;
    passive fibre k1 >= 0 (kPa), k2 > 0 (-); active T_max >= 0 (peak isometric stress),
    lam_opt > 0 (optimal fibre stretch, -), width > 0 (force-length width, -);
    lateral stiffness G_T >= 0 at rest and G_T_active >= 0 added at full activation;
    activation in [0, 1].
    """

    law = "Muscle"

    def __init__(self, C10: float, C20: float = 0.0, C30: float = 0.0, K: float = None,
                 k1: float = 0.0, k2: float = 1.0, T_max: float = 100.0, lam_opt: float = 1.0,
                 width: float = 0.5, G_T: float = 0.0, G_T_active: float = 0.0,
                 activation: float = 0.0, volumetric: str = "simo_taylor"):
        values = dict(C10=C10, C20=C20, C30=C30, K=K, k1=k1, k2=k2, T_max=T_max,
                      lam_opt=lam_opt, width=width, G_T=G_T, G_T_active=G_T_active,
                      activation=activation)
        check_parameters(self.law, values,
                         {"C10": ">0", "C20": "any", "C30": "any", "K": ">0", "k1": ">=0",
                          "k2": ">0", "T_max": ">=0", "lam_opt": ">0", "width": ">0",
                          "G_T": ">=0", "G_T_active": ">=0", "activation": ">=0"})
        if float(activation) > 1.0:
            raise MaterialError(f"{self.law}: parameter 'activation' must be in [0, 1], "
                                f"got {activation}", parameter="activation")
        if volumetric not in _VOLUMETRIC:
            raise MaterialError(f"{self.law}: volumetric must be one of {_VOLUMETRIC}, "
                                f"got {volumetric!r}", parameter="volumetric")
        for name, v in values.items():
            setattr(self, name, float(v))
        self.volumetric_kind = volumetric
        units = dict(C10="kPa", C20="kPa", C30="kPa", K="kPa", k1="kPa", k2="-", T_max="kPa",
                     lam_opt="-", width="-", G_T="kPa", G_T_active="kPa", activation="-")
        self.parameters = {k: (float(values[k]), units[k]) for k in units}

    def __repr__(self):
        p = ", ".join(f"{k}={v[0]:g}" for k, v in self.parameters.items())
        return f"{type(self).__name__}({p})"

    def with_activation(self, activation: float) -> "Muscle":
        """A copy of this muscle at another activation level."""
        kw = {k: v[0] for k, v in self.parameters.items()}
        kw["activation"] = activation
        return Muscle(**kw, volumetric=self.volumetric_kind)

    @property
    def shear_modulus(self) -> float:
        """Initial (small strain, passive, isotropic part) shear modulus 2 C10."""
        return 2.0 * self.C10

    # -- scalar derivatives of W_iso with respect to I1b and I4b ----------------------------
    def invariant_derivatives(self, I1b, I4b, load=1.0):
        """(W, W1, W4, W11, W14, W44) for the isochoric energy at activation a * load."""
        a = self.activation * float(load)
        t = I1b - 3.0
        W = self.C10 * t + self.C20 * t * t + self.C30 * t ** 3
        W1 = self.C10 + 2.0 * self.C20 * t + 3.0 * self.C30 * t * t
        W11 = 2.0 * self.C20 + 6.0 * self.C30 * t
        W4 = np.zeros_like(I4b)
        W44 = np.zeros_like(I4b)
        # passive fibres (tension only)
        if self.k1 > 0.0:
            s = np.maximum(I4b - 1.0, 0.0)
            arg = self.k2 * s * s
            e = np.exp(np.minimum(arg, _EXP_CAP))
            on = s > 0.0
            W = W + np.where(on, self.k1 / (2.0 * self.k2) * (e - 1.0), 0.0)
            W4 = W4 + np.where(on, self.k1 * s * e, 0.0)
            W44 = W44 + np.where(on, self.k1 * e * (1.0 + 2.0 * self.k2 * s * s), 0.0)
        # active fibre stress
        if a > 0.0 and self.T_max > 0.0:
            aT = a * self.T_max
            w = self.width
            u = 0.5 * np.log(I4b) - math.log(self.lam_opt)
            f = np.exp(-(u / w) ** 2)
            u1 = -math.log(self.lam_opt)
            c = aT * math.exp(0.25 * w * w) * w * math.sqrt(math.pi) / 2.0
            W = W + c * (erf(u / w - 0.5 * w) - math.erf(u1 / w - 0.5 * w))
            # dW/dI4b = (dW/dlam) / (2 lam), lam = sqrt(I4b); d f / dI4b = -f u / (w^2 I4b)
            r = I4b ** -0.5
            W4 = W4 + aT * f * r / (2.0 * self.lam_opt)
            W44 = W44 - aT * f * (1.0 + 2.0 * u / (w * w)) * r ** 3 / (4.0 * self.lam_opt)
        # lateral stiffness, growing with activation
        muT = self.G_T + a * self.G_T_active
        if muT > 0.0:
            r = I4b ** -0.5
            W = W + 0.5 * muT * (t + 3.0 - I4b - 2.0 * r)
            W1 = W1 + 0.5 * muT
            W4 = W4 + 0.5 * muT * (r ** 3 - 1.0)
            W44 = W44 - 0.75 * muT * r ** 5
        W14 = np.zeros_like(I1b)
        return W, W1, W4, W11, W14, W44

    def isochoric(self, C, fibres=None, load=1.0, tangent=True):
        C = np.asarray(C, dtype=float)
        I1b, dI1, d2I1, _, _ = i1_bar(C, second=tangent)
        if fibres is None:
            a0 = np.zeros(C.shape[:-1])
        else:
            a0 = np.broadcast_to(np.asarray(fibres, dtype=float), C.shape[:-1])
        I4b, dI4, d2I4 = i4_bar(C, a0, second=tangent)
        # Elements without a fibre direction (zero vector) behave as the isotropic matrix.
        has = np.einsum("...i,...i->...", a0, a0) > 0.5
        I4s = np.where(has, I4b, 1.0)
        W, W1, W4, W11, W14, W44 = self.invariant_derivatives(I1b, I4s, load)
        W4 = np.where(has, W4, 0.0)
        W44 = np.where(has, W44, 0.0)
        if not np.all(has):
            # remove the lateral term's I1 part where there is no fibre (pure matrix there)
            a = self.activation * float(load)
            muT = self.G_T + a * self.G_T_active
            W1 = np.where(has, W1, W1 - 0.5 * muT)
            W = np.where(has, W, W - 0.5 * muT * (I1b - 3.0))
        e2 = (..., None, None)
        e4 = (..., None, None, None, None)
        S = 2.0 * (W1[e2] * dI1 + W4[e2] * dI4)
        if not tangent:
            return S, None, W
        CC = 4.0 * (W11[e4] * outer(dI1, dI1)
                    + W14[e4] * (outer(dI1, dI4) + outer(dI4, dI1))
                    + W44[e4] * outer(dI4, dI4)
                    + W1[e4] * d2I1 + W4[e4] * d2I4)
        return S, CC, W

    def volumetric(self, J):
        return volumetric_function(self.volumetric_kind, self.K, J)

    # -- closed-form uniaxial response along the fibres (for checks and for users) ----------
    def uniaxial_fibre_stress(self, lam, load=1.0):
        """Cauchy stress sigma_11 of incompressible uniaxial stress along the fibres.

        F = diag(lam, lam^-1/2, lam^-1/2), fibre e1, lateral faces traction free:
        sigma_11 = 2 W1 (lam^2 - 1/lam) + 2 lam^2 W4 (the lateral term vanishes here), i.e.
        matrix + passive fibre + a T_max f(lam) lam / lam_opt.
        """
        lam = np.asarray(lam, dtype=float)
        I1b = lam ** 2 + 2.0 / lam
        I4b = lam ** 2
        _, W1, W4, _, _, _ = self.invariant_derivatives(I1b, I4b, load)
        return 2.0 * W1 * (lam ** 2 - 1.0 / lam) + 2.0 * I4b * W4
