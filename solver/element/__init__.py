"""Finite elements: the trilinear hexahedron, the bilinear quad facet and Gauss rules."""
from solver.element._hexahedron import (HEX8_CORNERS, HEX8_FACES, gauss_hex, gauss_quad,
                                        hex8_gradients, hex8_shape, quad4_gradients, quad4_shape)

__all__ = ["HEX8_CORNERS", "HEX8_FACES", "gauss_hex", "gauss_quad", "hex8_gradients",
           "hex8_shape", "quad4_gradients", "quad4_shape"]
