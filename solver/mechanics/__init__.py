"""Mechanics: the hyperelastic hexahedral solid (mean dilatation or displacement formulation)."""
from solver.mechanics._measures import von_mises
from solver.mechanics._solid import FORMULATIONS, Evaluation, SolidBody

__all__ = ["FORMULATIONS", "Evaluation", "SolidBody", "von_mises"]
