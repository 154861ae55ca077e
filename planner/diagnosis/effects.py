"""The effects a diagnosis can test, as named parameters with bounds and a "none" value.

Each effect of the contract (`sliding`, `muscle_tone`, `swelling`, `gravity`, `stiffness`,
`bone_execution`) is described once: its continuous parameters (the `--effect` name, the value
that gives exactly the baseline, plausible bounds, whether the fit works on the logarithm, the
finite-difference step) or its discrete choices (a switch such as `sliding=1`), and whether its
value is shared by every patient (a material property, the posture) or belongs to one case (a
surgical execution). The forward model of the diagnosis turns parameter values into the
`NAME=VALUE` strings of `faceplan predict --effect` and parses them with the pipeline's own
parser, so an effect plugs in as soon as the pipeline accepts it: `available_effects()` offers
only those that `planner.pipeline.parse_effects` takes.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from facemodel.effects import BONE_DOF, GRAVITY_MAX, LAYERS, SWELLING_MAX
from planner.errors import InputError

__all__ = ["Parameter", "Effect", "EFFECT_LIBRARY", "available_effects", "effect_strings", "stiffness_effect",
           "SLIDING_HOLDS", "MEASURED_MOVEMENT_SD"]


@dataclass(frozen=True)
class Parameter:
    """One continuous parameter: `key` is the `--effect` name (`stiffness.dermis`)."""

    key: str
    none: float
    lower: float
    upper: float
    step: float                 # finite-difference step in the fit coordinate
    log: bool = False           # the fit coordinate is log(value) (factors)
    unit: str = ""
    # standard deviation of the Gaussian prior about "none" in the fit coordinate (inf: flat,
    # the bounds alone), and the one that replaces it when the effect's measurement is given
    # (`Effect.measurement`): the parameter is then what remains on top of a measured value
    prior_sd: float = np.inf
    measured_sd: float | None = None

    def coordinate(self, value: float) -> float:
        return float(np.log(value)) if self.log else float(value)

    def value(self, coordinate: float) -> float:
        return float(np.exp(coordinate)) if self.log else float(coordinate)

    def prior(self, measured: bool = False) -> float:
        """The standard deviation of the parameter's Gaussian prior about "none" (fit
        coordinate, inf: flat); `measured`: its effect's measurement is in the model."""
        return self.measured_sd if measured and self.measured_sd is not None else self.prior_sd

    def dvalue(self, coordinate: float) -> float:
        """d value / d coordinate at `coordinate`: the chain rule's factor that turns a
        sensitivity per unit value into one per unit of the fit coordinate."""
        return self.value(coordinate) if self.log else 1.0

    @property
    def bounds(self) -> tuple[float, float]:
        return self.coordinate(self.lower), self.coordinate(self.upper)

    @property
    def origin(self) -> float:
        return self.coordinate(self.none)


@dataclass(frozen=True)
class Effect:
    """An effect: continuous `parameters` fitted to the gap, or discrete `choices` (each a
    mapping `--effect` name -> value) of which the best is taken."""

    name: str
    parameters: tuple[Parameter, ...] = ()
    choices: tuple[tuple[tuple[str, object], ...], ...] = ()
    shared: bool = False        # one value for every patient (left-one-case-out in a cohort)
    description: str = ""
    # settings of the chosen switch: (`--effect` name, values tried beside its default), each
    # chosen by the evidence under noise + discrepancy (`analysis`), e.g. how freely the tissue
    # slides (`SLIDING_HOLDS`)
    settings: tuple[tuple[str, tuple[float, ...]], ...] = ()
    # the choice that puts a measurement of the effect in the model (`bone_execution=1`: the
    # achieved movements of postop/plan_actual.yaml), under which the parameters are what
    # remains on top of it and take their `Parameter.measured_sd` prior
    measurement: tuple[tuple[str, object], ...] = ()

    def measured(self, choice=()) -> bool:
        """Is the effect's measurement among a case's discrete choices `choice`?"""
        return bool(self.measurement) and set(self.measurement) <= set(tuple(choice))

    @property
    def n_parameters(self) -> int:
        return (len(self.parameters) if self.parameters else (1 if self.choices else 0)) + len(self.settings)

    def values(self, theta: np.ndarray) -> dict[str, float]:
        """Fit coordinates -> {key: value} (parameters at their "none" value are left out)."""
        out = {}
        for p, t in zip(self.parameters, np.asarray(theta, float)):
            v = p.value(t)
            if not np.isclose(v, p.none, rtol=0, atol=1e-12):
                out[p.key] = round(v, 10)
        return out

    @property
    def origin(self) -> np.ndarray:
        return np.array([p.origin for p in self.parameters], float)


def _fmt(v) -> str:
    if isinstance(v, (list, tuple, np.ndarray)):
        return "[" + ", ".join(f"{float(x):.10g}" for x in v) + "]"
    if isinstance(v, (float, np.floating)):
        return f"{float(v):.10g}"
    return str(v)


def effect_strings(values: dict) -> tuple[str, ...]:
    """{key: value} -> sorted `NAME=VALUE` strings as `faceplan predict --effect` takes them."""
    return tuple(sorted(f"{k}={_fmt(v)}" for k, v in collect_effects(values).items()))


STIFFNESS_LAYERS = tuple(LAYERS)     # the model's stiffness layers, each a factor of its own
MOVED_SEGMENTS = ("maxilla", "mandible", "chin")

# Bounds are the plausible ranges of the effects' published values (see docs/diagnosis.md):
# resting perioral tone up to a third of maximal activation; tissue stiffness within a factor
# three of the generic values; swelling as the peak volumetric growth ratio up to the model's
# own bound (`facemodel.effects.SWELLING_MAX`: the residual 0.5-2 mm of skin at 3-12 months asks
# for peaks up to about 3, a synthetic truth may hold up to that bound, and a fit stopped below
# the value it needs leaves the rest of the gap to other effects);
# the posture change from supine to upright up to the model's own bound
# (`facemodel.effects.GRAVITY_MAX`), for the same reason as swelling: a truth drawn from the
# published skin change may need more than gravity's full effect on a softer face. A face
# fuller than the generic model over a whole region is the discrepancy's long scale, not
# swelling (`planner.diagnosis.discrepancy`).
EFFECT_LIBRARY: tuple[Effect, ...] = (
    Effect("sliding", choices=(), shared=False,
           description="soft tissue slides on the moved bone instead of being tied to it"),
    Effect("muscle_tone", (Parameter("muscle_tone", 0.0, 0.0, 0.35, 0.05, unit="activation"),),
           shared=False, description="resting activation of the perioral muscles"),
    Effect("swelling", (Parameter("swelling", 1.0, 1.0, SWELLING_MAX, 0.1, unit="volume ratio"),),
           shared=False, description="residual post-operative oedema (volumetric growth)"),
    Effect("gravity", (Parameter("gravity", 0.0, 0.0, GRAVITY_MAX, 0.25, unit="posture factor"),),
           shared=True, description="supine CT versus upright scan"),
    Effect("stiffness", (), shared=True,
           description="tissue stiffer or softer than the generic values"),
    Effect("bone_execution", (), shared=False, description="bones moved other than planned"),
)


def _accepted(strings: list[str]) -> bool:
    from planner.pipeline import parse_effects

    try:
        parse_effects(strings)
    except InputError:
        return False
    return True


def stiffness_effect(layers: bool = True) -> Effect | None:
    """The stiffness effect as the pipeline takes it: per-layer factors where it can
    (`layers`), else the uniform factor, None when it takes neither.
    The uniform factor is the direction along which every layer changes together: under
    displacement-only loading the data cannot see it, so one layer is left at "none" by the
    identifiability selection and the others are fitted relative to it."""
    base = next(e for e in EFFECT_LIBRARY if e.name == "stiffness")
    found = tuple(Parameter(f"stiffness.{layer}", 1.0, 1 / 3, 3.0, 0.2, log=True, unit="factor")
                  for layer in STIFFNESS_LAYERS if layers and _accepted([f"stiffness.{layer}=1.5"]))
    if found:
        return Effect("stiffness", found, shared=True, description=base.description)
    if _accepted(["stiffness=1.5"]):
        return Effect("stiffness", (Parameter("stiffness", 1.0, 1 / 3, 3.0, 0.2, log=True, unit="factor"),),
                      shared=True, description=base.description)
    return None


# how much the sliding interface resists the slide (`facemodel.effects` `sliding.hold`: 0 free,
# the switch's default, 1 tied), the values tried beside the free slide: a patient's tissue
# slides partly, and a model whose layers and moduli are not the patient's slides otherwise
# than the patient's tissue even where both slide freely. The interface smooths the slide as it
# holds (its pattern changes, not only its size), so the setting is a few full solves chosen
# by the evidence, not a derivative
SLIDING_HOLDS = (0.5, 0.8)


def _sliding(moved: tuple[str, ...]) -> Effect | None:
    """Which segments' tissue slides (every moved segment, or one of them) and how freely
    (`SLIDING_HOLDS`)."""
    base = next(e for e in EFFECT_LIBRARY if e.name == "sliding")
    choices = []
    if _accepted(["sliding=1"]):
        choices.append((("sliding", 1),))
    for seg in moved if len(moved) > 1 else ():       # one moved segment: the same as sliding=1
        if _accepted([f"sliding={seg}"]):
            choices.append((("sliding", seg),))
    if not choices:
        return None
    settings = (("sliding.hold", SLIDING_HOLDS),) if _accepted(["sliding=1", "sliding.hold=0.5"]) else ()
    return Effect("sliding", choices=tuple(choices), shared=False, description=base.description,
                  settings=settings)


# A segment's correction (planned-to-achieved difference): within +-3 mm and +-4 degrees per
# axis, the plausible range of published execution errors with the largest reported differences
# inside it (Stokbro et al., Int J Oral Maxillofac Surg 43:957, 2014, systematic review; Hsu et
# al., J Oral Maxillofac Surg 71:128, 2013), taken as the 95 % interval of a Gaussian prior, as
# the layer moduli's range is (`planner.diagnosis.analysis`, "Values marginal over the moduli"):
# a rotation and the translation it resembles at the skin are then not traded along a ridge the
# scan cannot resolve.
BONE_TRANSLATION_BOUND_MM = 3.0
BONE_ROTATION_BOUND_DEG = 4.0
# With the achieved movements measured (postop/plan_actual.yaml), the correction is what remains
# on top of the measurement: its prior is the measurement's accuracy. Superimposed post-op CBCT
# locates a segment's landmarks to about 0.3 mm (voxel- and surface-based superimposition
# errors below 0.2 mm, landmark differences of 0.2-0.3 mm), and a rotation to that over a lever
# arm of about 35 mm, 0.5 degrees. Without this prior a correction fitted on top of the
# measurement takes up the model's own form error.
MEASURED_MOVEMENT_SD = (0.3, 0.5)


def _bone_execution(moved: tuple[str, ...], plan_actual: bool = False) -> Effect | None:
    """Rigid corrections per moved segment: the three translations (mm) and three rotations
    (degrees, about the segment's centroid) of `bone_execution.SEGMENT=[tx, ty, tz, rx, ry,
    rz]`; with a `postop/plan_actual.yaml`, the achieved movements are a choice too."""
    params = []
    for seg in moved:
        if not _accepted([f"bone_execution.{seg}=[0.5, 0, 0, 0, 0, 0]"]):
            continue
        for i, dof in enumerate(BONE_DOF):
            bound = BONE_TRANSLATION_BOUND_MM if i < 3 else BONE_ROTATION_BOUND_DEG
            params.append(Parameter(f"bone_execution.{seg}.{dof}", 0.0, -bound, bound, 0.5,
                                    unit="mm" if i < 3 else "deg", prior_sd=bound / 1.96,
                                    measured_sd=MEASURED_MOVEMENT_SD[0 if i < 3 else 1]))
    achieved = (("bone_execution", 1),)
    choices = ((), achieved) if plan_actual and _accepted(["bone_execution=1"]) else ()
    if not params and not choices:
        return None
    return Effect("bone_execution", tuple(params), choices=choices, shared=False,
                  description="bones moved other than planned", measurement=achieved if choices else ())


def available_effects(moved_segments: tuple[str, ...] = MOVED_SEGMENTS,
                      names: tuple[str, ...] | None = None, *, plan_actual: bool = False,
                      stiffness_layers: bool = True,
                      executed_segments: tuple[str, ...] | None = None) -> list[Effect]:
    """The effects the pipeline can add to a prediction today (in the contract's order).
    `executed_segments`: the moved segments with an execution of their own, whose corrections
    `bone_execution` fits (default: every moved segment; the chin moving with the mandible,
    uncut, has none, `facemodel.effects.executed_segments`)."""
    out = []
    for e in EFFECT_LIBRARY:
        if names is not None and e.name not in names:
            continue
        if e.name == "sliding":
            spec = _sliding(moved_segments)
        elif e.name == "stiffness":
            spec = stiffness_effect(stiffness_layers)
        elif e.name == "bone_execution":
            spec = _bone_execution(moved_segments if executed_segments is None else executed_segments,
                                   plan_actual)
        else:
            p = e.parameters[0]
            spec = e if _accepted([f"{p.key}={_fmt(p.value(p.origin + p.step))}"]) else None
        if spec is not None:
            out.append(spec)
    return out


def collect_effects(values: dict) -> dict:
    """{key: value} with the flat bone-correction keys (`bone_execution.maxilla.tz`) gathered
    into the vectors `--effect bone_execution.maxilla=[tx, ty, tz, rx, ry, rz]` takes."""
    out: dict = {}
    vectors: dict[str, list] = {}
    for k, v in values.items():
        parts = k.split(".")
        if parts[0] == "bone_execution" and len(parts) == 3:
            vectors.setdefault(f"bone_execution.{parts[1]}", [0.0] * 6)[BONE_DOF.index(parts[2])] = float(v)
        else:
            out[k] = v
    for k, vec in vectors.items():
        out[k] = [round(x, 10) for x in vec]
    return out
