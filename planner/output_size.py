"""How much disk a prediction's outputs take, estimated before the solve from the mesh sizes.

`prediction_output_bytes` adds up an upper bound of each file `planner.pipeline.write_outputs`
writes, from the counts that fix its size: the FE mesh's nodes and hexahedra (`prediction.vtu`:
7 float64 values per node, connectivity, label and a 3x3 stress per cell, base64-encoded by
meshio (x 4/3); `model.feb`: one text line per node and per element, ~100 characters), the
triangles of the model's skin patch (`skin_predicted.stl/ply/vtp`), the vertices of the whole
predicted face (the patient's skin: `face_predicted.obj` ~160 characters per vertex with its
faces, `face_predicted.glb` ~60 bytes), and the pictures (PNG renders of mostly uniform
background compress to well under 1 byte per pixel; the bound takes 1; the turntable GIF has
at most 1 byte per pixel per frame), which `report.html` embeds again in base64 (x 4/3). The
total is multiplied by `MARGIN` for what the bound leaves out (file-system blocks, the
temporary copy of a small file, report tables growing with the landmarks). The sizes written
for the demo head and the synthetic heads lie between a quarter and a half of the estimate.
"""
from __future__ import annotations

# bytes per item, upper bounds of what the writers produce (see the module docstring)
VTU_BYTES_PER_NODE = 7 * 8 * 4 / 3
VTU_BYTES_PER_HEX = (8 * 8 + 8 + 1 + 4 + 9 * 8 + 8) * 4 / 3
FEB_BYTES_PER_NODE = 100
FEB_BYTES_PER_HEX = 120
PATCH_BYTES_PER_TRIANGLE = 50 + 13 + 40          # stl (binary) + ply (binary) + vtp
PATCH_BYTES_PER_VERTEX = 12 + 80                  # ply + vtp point data
FACE_BYTES_PER_VERTEX = 200 + 60                  # obj (vertex, normal, two faces) + glb
IMAGE_SIZE = (800, 800)                           # planner.render default window
IMAGE_COUNT = 2 * 6 + 3 + 1 + 1                   # pre/post x 6 views, 3 displacement, profile, overlay
TURNTABLE_BYTES = 20 * 320 * 320                  # 20 frames of 320 x 320, one byte per pixel
REPORT_BYTES = 2 * 2**20                          # report.json, landmarks, html text
MARGIN = 1.5
# Checked before the case is read: the smallest prediction (coarse mesh, a small skin, no
# pictures) writes ~3 MB; the estimate proper follows once the mesh is known.
PREDICT_FLOOR_MB = 10.0


def prediction_output_bytes(n_nodes: int, n_hexes: int, n_face_vertices: int, *,
                            n_patch_triangles: int | None = None, render: bool = True) -> int:
    """Upper estimate (bytes) of a prediction's output folder: a mesh of `n_nodes` nodes and
    `n_hexes` hexahedra, a whole face of `n_face_vertices` vertices, pictures when `render`.
    The model's skin patch has at most 2 triangles per surface node; without its count, the
    whole mesh's nodes bound it."""
    patch_triangles = 2 * n_nodes if n_patch_triangles is None else n_patch_triangles
    total = (n_nodes * (VTU_BYTES_PER_NODE + FEB_BYTES_PER_NODE)
             + n_hexes * (VTU_BYTES_PER_HEX + FEB_BYTES_PER_HEX)
             + patch_triangles * PATCH_BYTES_PER_TRIANGLE + patch_triangles // 2 * PATCH_BYTES_PER_VERTEX
             + n_face_vertices * FACE_BYTES_PER_VERTEX + REPORT_BYTES)
    if render:
        pictures = IMAGE_COUNT * IMAGE_SIZE[0] * IMAGE_SIZE[1] + TURNTABLE_BYTES
        total += pictures * (1 + 4 / 3)            # the files, and again in report.html
    return int(MARGIN * total)


def check_prediction_space(out_dir, resolution: str, patient_skin=None, *, render: bool = True) -> float:
    """Refuse (InputError, exit 2) an output location without room for the prediction at
    `resolution` on this patient skin (a trimesh or None), before any solve; return the
    estimate in MB."""
    import generic_mesh

    from planner.atomic import check_free_space

    model = generic_mesh.load(resolution)
    # the whole predicted face is the patient's skin (the model's skin patch without one)
    n_face = len(patient_skin.vertices) if patient_skin is not None else len(model.nodes)
    need_mb = prediction_output_bytes(len(model.nodes), len(model.hexes), n_face, render=render) / 2**20
    check_free_space(out_dir, need_mb, what=f"estimated size of the prediction's outputs at resolution "
                                            f"{resolution}, with a {MARGIN:g}x margin")
    return need_mb
