"""Default materials table of the face model, per element label (kPa, mm).

Every tissue is nearly incompressible and hyperelastic with the uncoupled Yeoh energy
W = C10 (I1b - 3) + C20 (I1b - 3)^2 + C30 (I1b - 3)^3 + U(J) (Yeoh O.H., Rubber Chem Technol
66:754-771, 1993), initial shear modulus mu = 2 C10 and bulk modulus K = 1000 mu (Poisson's
ratio 0.4995, the near incompressibility of water-rich soft tissue). Muscles add passive
fibre stiffening and an active fibre stress (the solver's `Muscle` law: T_max, optimal fibre
stretch lam_opt, force-length width, passive fibre k1/k2, cross-fibre stiffness G_T).

Sources of the numbers (`SOURCES` holds the key of each value):
* [gerard2005] passive face soft tissue C10 = 2.5 kPa, C20 = 1.175 kPa: Gerard J.-M., Ohayon
  J., Luboz V., Perrier P., Payan Y., Med Eng Phys 27:884-892, 2005 (indentation of facial
  tissue), the values of the Payan / Chabanas / Nazari face models (Nazari M.A. et al., J
  Biomech Eng 132:031002, 2010).
* [dermis] the dermis is several times stiffer than the subcutaneous fat (Joodaki H., Panzer
  M.B., Proc IMechE H 232:323-343, 2018, review); factor 4 on the face-tissue constants is our
  modelling choice within that range.
* [nose] nasal cartilage is in the MPa range (Richmon J.D. et al., Arch Facial Plast Surg
  7:20-25, 2005); the nose elements mix cartilage and soft tissue, so an effective factor 10
  on the face-tissue constants is our modelling choice (it keeps the nose shape while the
  lip moves under it).
* [incompressible] K = 1000 mu (nearly incompressible tissue, as used for the face by the
  same authors with Poisson ratios of 0.49 and above).
* [tmax] 100 kPa peak active stress for the thin facial muscles, below limb-muscle values of
  300 kPa (Blemker S.S., Pinsky P.M., Delp S.L., Ann Biomed Eng 33:661-673, 2005);
  lam_opt = 1 (muscles at rest length in the rest face) and force-length width 0.5 (Otten
  E., Exerc Sport Sci Rev 15:89-137, 1987 form): modelling choices.
* [fibre] passive fibre k1 = 2 kPa, k2 = 5 (Holzapfel-Gasser-Ogden exponential form) and
  cross-fibre stiffness G_T_active = 20 kPa at full activation (activated muscle stiffer
  across its fibres, Nazari et al. 2010): modelling choices of the same order as the matrix.

Constants of the sim-to-real effects (`facemodel.effects`, docs/effects.md):
* [swelling] resolution of post-operative swelling: about half gone at 3 weeks, ~80 % at 3
  months, ~93 % at 12 months (van der Vlis M., Dentino K.M., Vervloet B., Padwa B.L., J Oral
  Maxillofac Surg 72:2241-2247, 2014, 3D stereophotogrammetry; Kau C.H. et al. 2006).
* [density] soft-tissue density 1.05 g/cm^3 (Duck F.A., *Physical Properties of Tissue*, 1990),
  the gravity effect's rho.
* [pitch] natural head position scatters by a few degrees about the Frankfort horizontal
  (Cooke M.S., Wei S.H.Y., Am J Orthod Dentofacial Orthop 93:280-288, 1988): the gravity
  effect's head pitch is bounded at +-30 degrees.
"""
from __future__ import annotations

from dataclasses import dataclass, field

from facemodel.model import LABEL_NAMES, MUSCLES

C10_FACE = 2.5      # kPa [gerard2005]
C20_FACE = 1.175    # kPa [gerard2005]
BULK_FACTOR = 1000.0  # K / mu [incompressible]
DERMIS_FACTOR = 4.0   # [dermis]
NOSE_FACTOR = 10.0    # [nose]


@dataclass(frozen=True)
class MaterialEntry:
    """One row of the table: the solver law name and its keyword parameters (kPa)."""

    label: str
    law: str                       # "Yeoh" or "Muscle" (classes of solver.constitution)
    parameters: dict
    sources: dict = field(default_factory=dict)

    @property
    def shear_modulus(self) -> float:
        return 2.0 * self.parameters["C10"]


def _yeoh(factor: float, src: str) -> dict:
    c10, c20 = factor * C10_FACE, factor * C20_FACE
    return dict(C10=c10, C20=c20, C30=0.0, K=BULK_FACTOR * 2.0 * c10), \
        dict(C10=src, C20=src, C30=src, K="incompressible")


def _build() -> dict:
    table = {}
    for label in LABEL_NAMES:
        if label == "dermis":
            p, s = _yeoh(DERMIS_FACTOR, "dermis")
        elif label == "nose":
            p, s = _yeoh(NOSE_FACTOR, "nose")
        else:
            p, s = _yeoh(1.0, "gerard2005")
        if label in MUSCLES:
            p.update(k1=2.0, k2=5.0, T_max=100.0, lam_opt=1.0, width=0.5, G_T=0.0, G_T_active=20.0)
            s.update(k1="fibre", k2="fibre", T_max="tmax", lam_opt="tmax", width="tmax",
                     G_T="fibre", G_T_active="fibre")
            table[label] = MaterialEntry(label, "Muscle", p, s)
        else:
            table[label] = MaterialEntry(label, "Yeoh", p, s)
    return table


MATERIALS: dict = _build()
SOURCES = {
    "gerard2005": "Gerard et al., Med Eng Phys 27:884-892, 2005 (face C10 = 2.5, C20 = 1.175 kPa)",
    "dermis": "dermis stiffer than fat (Joodaki & Panzer 2018 review); factor 4: modelling choice",
    "nose": "nasal cartilage MPa-range (Richmon et al. 2005); effective factor 10: modelling choice",
    "incompressible": "K = 1000 mu, nearly incompressible soft tissue",
    "tmax": "T_max 100 kPa (below 300 kPa of Blemker et al. 2005); lam_opt 1, width 0.5: choices",
    "fibre": "passive fibre k1 2 kPa, k2 5; G_T_active 20 kPa (Nazari et al. 2010, qualitative): choices",
}


def material(label: str) -> MaterialEntry:
    """The table row of a label (KeyError naming the known labels otherwise)."""
    try:
        return MATERIALS[label]
    except KeyError:
        raise KeyError(f"no material for label {label!r}; labels: {', '.join(LABEL_NAMES)}") from None


# the parameters a stiffness factor scales (moduli; not the active stress or shape parameters)
MODULI = ("C10", "C20", "C30", "K", "k1", "G_T", "G_T_active")


def parameters(label: str, stiffness: float = 1.0) -> dict:
    """Solver keyword parameters of a label; `stiffness` scales every modulus (C10, C20, C30,
    K, k1, G_T, G_T_active), e.g. for the 'stiffness' effect, leaving the active stress."""
    p = dict(material(label).parameters)
    for key in MODULI:
        if key in p:
            p[key] = p[key] * stiffness
    return p


def table_rows() -> list:
    """The table as rows for a report: label, law, parameters, sources."""
    return [dict(label=e.label, law=e.law, parameters=dict(e.parameters),
                 sources={k: SOURCES[v] for k, v in e.sources.items()}) for e in MATERIALS.values()]


def solver_material(label: str, params: dict):
    """The solver material object (solver.constitution `Yeoh` / `Muscle`, the table's law of
    `label`) with keyword parameters `params`."""
    from solver.constitution import Yeoh
    from solver.constitution.muscle import Muscle

    return {"Yeoh": Yeoh, "Muscle": Muscle}[material(label).law](**params)


def default_materials(model=None, stiffness: float = 1.0) -> dict:
    """Solver material objects per label (solver.constitution `Yeoh` / `Muscle`), for the
    labels of `model` (all labels of the table when None)."""
    labels = LABEL_NAMES if model is None else tuple(model.label_names)
    return {label: solver_material(label, parameters(label, stiffness)) for label in labels}
