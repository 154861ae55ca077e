"""The solver settings of the face model: one named object, `FACE_SOLVER`.

`solver.newton.newton_solve` and the contact terms have generic defaults; the face, nearly
incompressible soft tissue with lip-lip and lip-teeth contact under large prescribed bone
motions, is solved with the values gathered here, each with the reason it holds. They were
chosen on the synthetic faces of `bench/contact.py`, `bench/pipeline.py` and `faceplan synth`;
`FaceSolverSettings.control` turns them into a `solver.control.SolverControl`.
"""
from __future__ import annotations

from dataclasses import dataclass

from solver.control import SolverControl

__all__ = ["FaceSolverSettings", "FACE_SOLVER"]


@dataclass(frozen=True)
class FaceSolverSettings:
    """Newton and contact settings of the face.

    rtol, etol: relative residual and energy tolerances. Node-to-surface contact near facet
    edges has a clamped curvature term, so the last digits converge linearly: a tight energy
    tolerance with a moderate residual one converges without chasing round-off.
    max_retries: re-solves of one load step the contact terms may ask for (status changes
    and augmentations of the lips and teeth together).
    stall_iterations (with contact): a step whose residual has not fallen to a tenth after
    that many iterations is cut back at once; contact switching within too large a step makes
    Newton wander, and the remaining iterations of a lost step are saved.
    shrink_iterations: a step whose first solve needed more iterations halves the next: a hard
    step on the face announces a harder one (contact closing), and halving costs less than a
    cut-back.
    blowup_factor: the Newton blow-up guard (`SolverControl.blowup_factor`; None: off). On the
    face an update can drive a muscle or fat element next to degeneracy without inverting
    it; taken, such an iterate led a fine truth solve into many crawling iterations and
    continuation (docs/effects.md).
    augmentation_rtol: a solve whose relative residual is below it stops when the contact
    terms will augment the step anyway (the multiplier update need not wait for a converged
    penalty solve).
    increment_fraction: no contact node moves more than this fraction of the lip facets' size
    in one Newton iteration (contact switching on can make an undamped update overshoot); the
    other free nodes follow the bones by several mm per step and are not limited. Larger lets
    an update reach contact in one go but overshoots; smaller spends iterations creeping.
    teeth_increment_fraction: the limit is never below this fraction of the teeth's advance in
    one load step (the largest displacement of a tooth vertex over the first step). The teeth
    are rigid surfaces at the step's target from its first iteration, so the mucosa in front
    of them has to move by their advance within the step; a limit that is a fraction of the
    lip facets alone shrinks with the mesh while the advance does not, and a finer mesh then
    creeps behind the teeth for more iterations, with the mucosa squeezed between the teeth
    and the tissue still held back, until the step stalls. At 1 one limited iteration carries
    the mucosa over the teeth's advance at every resolution; at 0.5 (two iterations) the fine
    truths' first load steps still stalled where the mucosa touches the other lip and the
    incisors at once (docs/effects.md, "The increment limit follows the teeth").
    pair_hysteresis: a lip node keeps its master triangle while its projection is within this
    barycentric distance outside it (a node over a crease otherwise flips between two planes).
    lip_crease_blend, lip_edge_release: crease blending and the release band of the lip-lip
    contact (`SurfaceContact`'s `crease_blend`, `edge_release`; fractions of a facet edge),
    off (0): on held-out seed 1016 at standard (docs/solver_control.md, Limitations) neither
    passed the pinched stomion corner, and each changes the Newton path of every face solve.
    lip_penalty: factor on the lip-lip contact penalty (of 3 mu / h, mu the lips' shear
    modulus, h their facet size), 1. A softer penalty lets the pinched stomion corner of
    held-out seeds 1016 and 1017 reach full load, but only by ending its augmentations with
    the lips up to 0.5 mm inside each other (tolerance 0.05 mm); more augmentations fail at
    full load as the full penalty does (docs/solver_control.md, "The lip-lip penalty").
    fallback_lip_penalties: a face solve with lip contact that fails is solved again from the
    start with the lip-lip penalty times each of these in turn (0.1, then 0.03: about half a
    decade each) until one converges, its final load left at the penalty solution with the
    carried multipliers (the augmentations that fail there are not made); the penetration left
    is reported as an unmet contact, and the fallback in the solve's info (`contact_fallback`).
    Empty: no fallback. Where the nominal solve fails at a pinched stomion corner (held-out
    seeds 1016 and 1017 at standard), the softer penalty passes the corner; only the final
    augmentations fail there (docs/solver_control.md). At 0.03 the lips already end about 1 mm
    inside each other (held-out seed 1017's face scan), so the sequence ends there.
    fallback_budget_share: with a wall-clock budget, each solve of that sequence but the last
    gets this share of what is left of it (the nominal half, the first fallback a quarter, the
    second the rest), so that a nominal solve creeping at a limit point of the lips cannot
    spend the whole budget before the softer contact is tried; without a budget, or without
    fallbacks, the one solve has all of it.
    """

    rtol: float = 1e-6
    etol: float = 1e-8
    max_retries: int = 20
    stall_iterations: int = 8
    shrink_iterations: int = 7
    blowup_factor: float | None = 100.0
    augmentation_rtol: float = 0.5
    increment_fraction: float = 0.35
    teeth_increment_fraction: float = 1.0
    pair_hysteresis: float = 0.05
    lip_crease_blend: float = 0.0
    lip_edge_release: float = 0.0
    lip_penalty: float = 1.0
    fallback_lip_penalties: tuple = (0.1, 0.03)
    fallback_budget_share: float = 0.5

    def max_increment(self, lip_size: float | None, teeth_advance: float = 0.0) -> float:
        """The increment limit (mm) of a contact node: `increment_fraction` of the lip facets'
        median edge `lip_size` (2 mm when None), at least `teeth_increment_fraction` of
        `teeth_advance`, the teeth's largest advance in one load step (mm)."""
        return max(self.increment_fraction * (lip_size or 2.0),
                   self.teeth_increment_fraction * float(teeth_advance or 0.0))

    def control(self, steps: int, max_iterations: int, contact_nodes=None,
                lip_size: float | None = None, teeth_advance: float = 0.0) -> SolverControl:
        """The `SolverControl` of one face solve; `contact_nodes` None without contact terms.
        lip_size: the lip facets' median edge (mm; 2 mm when the lips have no contact);
        teeth_advance: the teeth's largest advance in the first load step (mm, 0 without
        teeth contact)."""
        contact = contact_nodes is not None
        return SolverControl(
            steps=steps, max_iterations=max_iterations, rtol=self.rtol, etol=self.etol,
            max_retries=self.max_retries, shrink_iterations=self.shrink_iterations,
            blowup_factor=self.blowup_factor,
            stall_iterations=self.stall_iterations if contact else None,
            max_increment=self.max_increment(lip_size, teeth_advance) if contact else None,
            increment_nodes=contact_nodes, augmentation_rtol=self.augmentation_rtol)


FACE_SOLVER = FaceSolverSettings()
