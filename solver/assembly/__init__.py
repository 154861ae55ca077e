"""Assembly: numba element kernels and the fixed upper-triangle sparsity pattern."""
from solver.assembly._kernels import (element_matrices, element_residuals, scatter_packed,
                                      scatter_upper, scatter_vector, upper_pairs)
from solver.assembly._pattern import UpperPattern, element_dofs

__all__ = ["element_matrices", "element_residuals", "scatter_packed", "scatter_upper",
           "scatter_vector",
           "upper_pairs", "UpperPattern", "element_dofs"]
