"""FaceModel: the labelled hexahedral face and everything anatomical attached to it.

One frozen dataclass brings together the mesh (nodes in mm, RAS; hexahedra in VTK order),
element labels and fibre directions, bone attachments and free deep surfaces (node sets),
contact surfaces (quad facet sets, outward by the right-hand rule), rigid teeth per bone
segment, skin regions and soft-tissue landmarks (node indices), as agreed in the shared
interfaces. Stored as a VTU file (meshio; cell data `label`, `fibre`) with a JSON sidecar of
the same stem holding the sets; derived quantities (skin triangle surface, landmark
positions, per-label element lists) are cached properties, in the spirit of trimesh.
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field, replace
from functools import cached_property
from pathlib import Path

import numpy as np

LABEL_NAMES = (
    "dermis", "hypodermis", "mucosa", "nose", "orbicularis_oris", "zygomaticus_major",
    "levator_labii_superioris", "risorius", "buccinator", "depressor_anguli_oris",
    "depressor_labii_inferioris", "mentalis",
)
MUSCLES = LABEL_NAMES[4:]
SEGMENTS = ("skull", "maxilla", "mandible", "chin")
ATTACHMENT_SETS = {"skull": "attach_skull", "maxilla": "attach_maxilla",
                   "mandible": "attach_mandible", "chin": "attach_chin"}
# the boundary conditions of the mesh's cut through the neck (node set "neck"; `facemodel.simulation`)
NECK_CONDITIONS = ("free", "held")
# the boundary conditions of the free deep surface under the mandible (node set
# "floor_of_mouth"; `facemodel.simulation`)
FLOOR_CONDITIONS = ("free", "held")
# what the mandible's proximal segments (node set "mandible_proximal": ramus and angle) do when
# the plan moves the mandible: "seated", a sagittal split leaves them with the condyles in the
# fossae; "moved", the whole mandible moves as one body (`facemodel.attachments`)
PROXIMAL_CONDITIONS = ("seated", "moved")
PROXIMAL_SET = "mandible_proximal"
LANDMARK_NAMES = ("Prn", "Sn", "Ls", "Stms", "Stmi", "Li", "ChL", "ChR", "Pog", "Me")
FORMAT_VERSION = 1


@dataclass(frozen=True, eq=False)
class FaceModel:
    nodes: np.ndarray
    hexes: np.ndarray
    labels: np.ndarray
    label_names: tuple
    fibres: np.ndarray
    node_sets: dict = field(default_factory=dict)
    facet_sets: dict = field(default_factory=dict)
    teeth: dict = field(default_factory=dict)
    regions: dict = field(default_factory=dict)
    unoperated_regions: tuple = ()
    landmarks: dict = field(default_factory=dict)
    segments: tuple = SEGMENTS

    # ------------------------------------------------------------------ derived
    @property
    def n_nodes(self) -> int:
        return len(self.nodes)

    @property
    def n_elements(self) -> int:
        return len(self.hexes)

    def label_id(self, name: str) -> int:
        return self.label_names.index(name)

    def elements_with_label(self, name: str) -> np.ndarray:
        return np.flatnonzero(self.labels == self.label_id(name))

    @cached_property
    def element_centres(self) -> np.ndarray:
        return self.nodes[self.hexes].mean(axis=1)

    @cached_property
    def landmark_positions(self) -> dict:
        return {k: self.nodes[v].copy() for k, v in self.landmarks.items()}

    @cached_property
    def skin_surface(self):
        """The skin as a trimesh.Trimesh (vertices = all model nodes; unused ones kept so that
        vertex i is node i)."""
        import trimesh

        q = self.facet_sets["skin"]
        tri = np.concatenate([q[:, [0, 1, 2]], q[:, [0, 2, 3]]])
        return trimesh.Trimesh(self.nodes, tri, process=False)

    @cached_property
    def skin_region_of_node(self) -> np.ndarray:
        """(n,) index into `region_names` of each node's skin region, -1 for none."""
        out = np.full(self.n_nodes, -1, dtype=int)
        for i, name in enumerate(self.region_names):
            out[self.regions[name]] = i
        return out

    @property
    def region_names(self) -> tuple:
        return tuple(sorted(self.regions))

    def teeth_mesh(self, name: str):
        import trimesh

        v, f, _ = self.teeth[name]
        return trimesh.Trimesh(np.asarray(v, float), np.asarray(f, int), process=False)

    def with_nodes(self, nodes: np.ndarray, teeth: dict | None = None) -> "FaceModel":
        """The same model on moved nodes (e.g. after registration)."""
        nodes = np.asarray(nodes, dtype=float)
        if nodes.shape != self.nodes.shape:
            raise ValueError(f"nodes must have shape {self.nodes.shape}, got {nodes.shape}")
        return replace(self, nodes=nodes, teeth=self.teeth if teeth is None else teeth)

    # --------------------------------------------------------------------- I/O
    def save(self, path) -> None:
        """Write `path` (.vtu) and its JSON sidecar (same stem, .json)."""
        import meshio

        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        # point data for viewing (ParaView): attachment segment (index into `segments`, len =
        # free deep node, -1 none) and skin region (index into sorted region names, -1 none)
        attach = np.full(self.n_nodes, -1, dtype=np.int32)
        for i, seg in enumerate(self.segments):
            attach[self.node_sets.get(ATTACHMENT_SETS.get(seg, ""), [])] = i
        attach[self.node_sets.get("deep_free", [])] = len(self.segments)
        mesh = meshio.Mesh(
            self.nodes, [("hexahedron", np.asarray(self.hexes, dtype=np.int64))],
            point_data={"attachment": attach, "region": self.skin_region_of_node.astype(np.int32)},
            cell_data={"label": [np.asarray(self.labels, dtype=np.int32)],
                       "fibre": [np.asarray(self.fibres, dtype=float)]},
        )
        mesh.write(path, binary=True, compression="zlib")
        side = {
            "format": "faceplan-facemodel", "version": FORMAT_VERSION,
            "label_names": list(self.label_names),
            "node_sets": {k: np.asarray(v).tolist() for k, v in self.node_sets.items()},
            "facet_sets": {k: np.asarray(v).tolist() for k, v in self.facet_sets.items()},
            "teeth": {k: {"vertices": np.round(np.asarray(v, float), 6).tolist(),
                          "faces": np.asarray(f).tolist(), "segment": s}
                      for k, (v, f, s) in self.teeth.items()},
            "regions": {k: np.asarray(v).tolist() for k, v in self.regions.items()},
            "unoperated_regions": list(self.unoperated_regions),
            "landmarks": {k: int(v) for k, v in self.landmarks.items()},
            "segments": list(self.segments),
        }
        path.with_suffix(".json").write_text(json.dumps(side, separators=(",", ":")))

    @classmethod
    def load(cls, path) -> "FaceModel":
        import meshio

        path = Path(path)
        mesh = meshio.read(path)
        side = json.loads(path.with_suffix(".json").read_text())
        hexes = np.concatenate([c.data for c in mesh.cells if c.type == "hexahedron"])
        labels = np.concatenate(mesh.cell_data["label"]).astype(int)
        fibres = np.concatenate(mesh.cell_data["fibre"]).astype(float)
        ints = lambda d: {k: np.asarray(v, dtype=int) for k, v in d.items()}  # noqa: E731
        return cls(
            nodes=np.asarray(mesh.points, dtype=float), hexes=hexes.astype(int), labels=labels,
            label_names=tuple(side["label_names"]), fibres=fibres,
            node_sets=ints(side["node_sets"]),
            facet_sets={k: np.asarray(v, dtype=int).reshape(-1, 4) for k, v in side["facet_sets"].items()},
            teeth={k: (np.asarray(t["vertices"], float), np.asarray(t["faces"], int), t["segment"])
                   for k, t in side["teeth"].items()},
            regions=ints(side["regions"]), unoperated_regions=tuple(side["unoperated_regions"]),
            landmarks={k: int(v) for k, v in side["landmarks"].items()},
            segments=tuple(side["segments"]),
        )
