"""Constitutive laws: the material protocol and uncoupled hyperelastic materials."""
from solver.constitution.base import Material, check_parameters, i1_bar, i4_bar
from solver.constitution._hyperelastic import NeoHooke, Yeoh, volumetric_function

__all__ = ["Material", "check_parameters", "i1_bar", "i4_bar", "NeoHooke", "Yeoh",
           "volumetric_function"]
