"""Essential boundary conditions: prescribed nodal displacements and local-frame constraints.

`Prescribed` fixes Cartesian displacement components of nodes, ramped with the load fraction
(u(load) = load * u, or a callable load -> (k, 3) for non-linear paths such as rigid rotations).
`LocalFrame` constrains chosen components of the displacement in a per-node orthonormal frame
(rows of `frames[i]` are the local axes), e.g. only the normal component so that a node may
slide tangentially on a (moving) surface. The solver works in the transformed unknowns
u_hat = T u, with T block diagonal (the frame rotations, identity elsewhere), so a local
constraint becomes a constrained unknown (Zienkiewicz & Taylor, *The FEM*, vol. 1, sec. 10.4).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from solver.errors import BoundaryConditionError

__all__ = ["Prescribed", "LocalFrame", "fix", "ConstraintSet", "ramped_values"]


def ramped_values(spec, nodes, load):
    """The (k, 3) nodal values of `spec` at load fraction `load`: load * spec for a constant
    (3,) or (k, 3) spec (a linear ramp), spec(load) for a callable (a non-linear path)."""
    if callable(spec):
        v = np.asarray(spec(load), dtype=float)
    else:
        v = load * np.asarray(spec, dtype=float)
    return np.broadcast_to(v, (len(nodes), 3))


@dataclass(frozen=True, eq=False)
class Prescribed:
    """Prescribed displacement components of nodes.

    nodes (k,); displacement (3,), (k, 3) or callable load -> (k, 3) (mm) at load fraction 1;
    components: which Cartesian components are prescribed (0 = x, 1 = y, 2 = z).
    """

    nodes: np.ndarray
    displacement: object = 0.0
    components: tuple = (0, 1, 2)

    def __post_init__(self):
        nodes = np.atleast_1d(np.asarray(self.nodes, dtype=np.int64))
        object.__setattr__(self, "nodes", nodes)
        comps = tuple(int(c) for c in self.components)
        if not comps or any(c not in (0, 1, 2) for c in comps) or len(set(comps)) != len(comps):
            raise BoundaryConditionError(f"components must be distinct values of 0, 1, 2; got {comps}")
        object.__setattr__(self, "components", comps)
        if not callable(self.displacement):
            d = np.asarray(self.displacement, dtype=float)
            if d.shape not in ((), (3,), (len(nodes), 3)):
                raise BoundaryConditionError(
                    f"displacement must be a scalar, (3,) or ({len(nodes)}, 3); got {d.shape}")
            if not np.all(np.isfinite(d)):
                raise BoundaryConditionError("prescribed displacement is not finite")

    def values(self, load: float) -> np.ndarray:
        return ramped_values(self.displacement, self.nodes, load)


def fix(nodes, components=(0, 1, 2)) -> Prescribed:
    """Zero displacement of the given components of nodes."""
    return Prescribed(nodes, 0.0, components)


@dataclass(frozen=True, eq=False)
class LocalFrame:
    """Constrain displacement components of nodes in a local orthonormal frame per node.

    frames (k, 3, 3) or (3, 3): rows are the local axes; fixed: local components constrained;
    displacement: optional (3,), (k, 3) or callable load -> (k, 3) global displacement whose
    projection on the fixed local axes is imposed (e.g. the motion of the bone the node slides
    on); zero by default.
    """

    nodes: np.ndarray
    frames: np.ndarray
    fixed: tuple = (0,)
    displacement: object = 0.0

    def __post_init__(self):
        nodes = np.atleast_1d(np.asarray(self.nodes, dtype=np.int64))
        frames = np.asarray(self.frames, dtype=float)
        if frames.shape == (3, 3):
            frames = np.broadcast_to(frames, (len(nodes), 3, 3))
        if frames.shape != (len(nodes), 3, 3):
            raise BoundaryConditionError(f"frames must have shape ({len(nodes)}, 3, 3), got {frames.shape}")
        err = np.abs(np.einsum("kij,klj->kil", frames, frames) - np.eye(3)).max() if len(nodes) else 0
        if not err < 1e-8:
            raise BoundaryConditionError(f"local frames must be orthonormal (rows), error {err:.2g}")
        dets = np.linalg.det(frames) if len(nodes) else np.ones(0)
        frames = np.where(dets[:, None, None] < 0, frames * np.array([1, 1, -1.0])[:, None], frames)
        fixed = tuple(int(c) for c in self.fixed)
        if any(c not in (0, 1, 2) for c in fixed) or len(set(fixed)) != len(fixed):
            raise BoundaryConditionError(f"fixed must be distinct values of 0, 1, 2; got {fixed}")
        object.__setattr__(self, "nodes", nodes)
        object.__setattr__(self, "frames", np.ascontiguousarray(frames))
        object.__setattr__(self, "fixed", fixed)

    def values(self, load: float) -> np.ndarray:
        return ramped_values(self.displacement, self.nodes, load)


@dataclass
class ConstraintSet:
    """All essential conditions of a problem in transformed unknowns u_hat = T u.

    rot (n, 3, 3) node rotations (identity where no frame), has_frame (n,), dofs: constrained
    transformed dofs (sorted), and a function giving their target values at a load fraction.
    Nodes touched by no element are held fixed.
    """

    n_nodes: int
    constraints: list
    unused_nodes: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))

    def __post_init__(self):
        n = self.n_nodes
        self.rot = np.broadcast_to(np.eye(3), (n, 3, 3)).copy()
        self.has_frame = np.zeros(n, dtype=bool)
        owner = {}
        for k, c in enumerate(self.constraints):
            if not isinstance(c, (Prescribed, LocalFrame)):
                raise BoundaryConditionError(f"constraint {k} is neither Prescribed nor LocalFrame")
            if len(c.nodes) and (c.nodes.min() < 0 or c.nodes.max() >= n):
                raise BoundaryConditionError(f"constraint {k} refers to nodes outside 0..{n - 1}")
            if isinstance(c, LocalFrame):
                if np.any(self.has_frame[c.nodes]):
                    dup = c.nodes[self.has_frame[c.nodes]][:5].tolist()
                    raise BoundaryConditionError(f"nodes {dup} have more than one local frame")
                self.rot[c.nodes] = c.frames
                self.has_frame[c.nodes] = True
        for k, c in enumerate(self.constraints):
            if isinstance(c, Prescribed) and np.any(self.has_frame[c.nodes]):
                dup = c.nodes[self.has_frame[c.nodes]][:5].tolist()
                raise BoundaryConditionError(
                    f"nodes {dup} have both a local frame and Cartesian prescribed components; "
                    f"prescribe them in the frame (LocalFrame.fixed) instead")
        dofs = []
        for c in self.constraints:
            comps = c.components if isinstance(c, Prescribed) else c.fixed
            dofs.append((3 * c.nodes[:, None] + np.asarray(comps)[None, :]).ravel())
        unused = np.asarray(self.unused_nodes, dtype=np.int64)
        dofs.append((3 * unused[:, None] + np.arange(3)[None, :]).ravel())
        alld = np.concatenate(dofs) if dofs else np.zeros(0, dtype=np.int64)
        self.dofs = np.unique(alld)
        self.mask = np.zeros(3 * n, dtype=bool)
        self.mask[self.dofs] = True
        self.free = np.nonzero(~self.mask)[0]
        self.any_frame = bool(self.has_frame.any())

    def targets(self, load: float, X: np.ndarray) -> np.ndarray:
        """Target transformed displacements u_hat at all constrained dofs, (n_c,) in self.dofs order."""
        full = np.zeros(3 * self.n_nodes)
        for c in self.constraints:
            v = c.values(load)
            if isinstance(c, Prescribed):
                idx = (3 * c.nodes[:, None] + np.asarray(c.components)[None, :])
                full[idx.ravel()] = v[:, list(c.components)].ravel()
            else:
                loc = np.einsum("kij,kj->ki", c.frames, v)
                idx = (3 * c.nodes[:, None] + np.asarray(c.fixed)[None, :])
                full[idx.ravel()] = loc[:, list(c.fixed)].ravel()
        return full[self.dofs]

    # transforms between global and local (hatted) dof vectors
    def to_local(self, v: np.ndarray) -> np.ndarray:
        if not self.any_frame:
            return v
        return np.einsum("nij,nj->ni", self.rot, v.reshape(-1, 3)).ravel()

    def to_global(self, v: np.ndarray) -> np.ndarray:
        if not self.any_frame:
            return v
        return np.einsum("nji,nj->ni", self.rot, v.reshape(-1, 3)).ravel()
