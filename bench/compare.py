"""Benchmark: `faceplan compare` on a 100k-vertex post-op scan (issue 7: under 10 s).

Builds a case in a temporary folder -- the analytic face phantom as the prediction (1.5 mm
triangulation, ~22k vertices, like the standard FE skin) and an independent ~100k-vertex
triangulation of the same face, moved rigidly and with 0.2 mm noise, as the post-op STL scan --
then times the whole command (reading, superimposition, distances both ways, landmarks,
pictures, reports) after one warm-up run on a small case (numba compilation is cached and not
part of a user's run). Prints the figures; the last line is `compare_s=<seconds>`.
"""
from __future__ import annotations

import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import trimesh

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from planner.cli import main  # noqa: E402
from planner.compare.alignment import apply, rotation_matrix  # noqa: E402
from planner.compare.phantom import face_phantom, write_prediction_folder  # noqa: E402


def make_case(root: Path, scan_spacing: float, seed: int = 0) -> tuple[Path, int]:
    pred = face_phantom(1.5)
    scan = face_phantom(scan_spacing, jitter=0.6, seed=seed, offset=0.31)
    write_prediction_folder(root / "predict", pred.vertices, pred.faces, pred.region,
                            pred.region_names, pred.landmarks, pred.unoperated_regions)
    rng = np.random.default_rng(seed)
    T = np.eye(4)
    T[:3, :3] = rotation_matrix(np.radians([3.0, -2.0, 4.0]))
    T[:3, 3] = [2.0, -3.0, 1.5]
    v = apply(T, scan.vertices + rng.normal(scale=0.2, size=scan.vertices.shape))
    (root / "postop").mkdir(parents=True)
    trimesh.Trimesh(v, scan.faces, process=False).export(root / "postop" / "skin.stl")
    return root, len(scan.vertices)


def run() -> None:
    with tempfile.TemporaryDirectory() as tmp:
        small, _ = make_case(Path(tmp) / "warm", 2.5)
        assert main(["compare", str(small), "--no-images"]) == 0
        case, n = make_case(Path(tmp) / "big", 0.7)
        print(f"post-op scan vertices: {n}")
        t0, c0 = time.perf_counter(), time.process_time()
        assert main(["compare", str(case), "--no-images"]) == 0
        t_core, c_core = time.perf_counter() - t0, time.process_time() - c0
        print(f"compare without pictures: {t_core:.2f} s wall, {c_core:.2f} s CPU")
        t0, c0 = time.perf_counter(), time.process_time()
        assert main(["compare", str(case)]) == 0
        t_all, c_all = time.perf_counter() - t0, time.process_time() - c0
        # on a shared machine wall time exceeds CPU time; both are printed
        print(f"compare with pictures and report: {t_all:.2f} s wall, {c_all:.2f} s CPU")
        print(f"compare_s={t_all:.2f}")


if __name__ == "__main__":
    run()
