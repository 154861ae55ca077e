"""Property-based: no malformed plan crashes with a traceback. Whatever the YAML tree or text,
`parse_plan` / `load_plan` either return a Plan whose movements are rigid or raise InputError;
the CLI maps InputError to exit 2."""
import copy

import numpy as np
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from planner.errors import InputError
from planner.plan import load_plan, parse_plan

VALID = {
    "faceplan": 1,
    "frame": "RAS",
    "segments": {
        "maxilla": {"translation": [0.0, 4.0, 1.5],
                    "rotation": {"axis": [1, 0, 0], "angle_deg": -3.0, "center": [0, 62, -18]}},
        "mandible": {"matrix": [[1, 0, 0, 0], [0, 1, 0, -6.0], [0, 0, 1, 0], [0, 0, 0, 1]]},
        "chin": {"rotation": {"euler_deg": [2, 0, 0], "order": "xyz", "center": [0, 70, -50]},
                 "from": "mandible", "cut_planes": [{"point": [0, 0, -40], "normal": [0, 0, -1]}]},
    },
    "muscles": {"orbicularis_oris": 0.1},
    "model": {"resolution": "coarse", "sliding": False, "contact": True,
              "materials": {"dermis": {"c10": 2.5}}, "effects": {"sliding": 1}},
    "limits": {"translation_mm": 25, "rotation_deg": 30},
}
KEYS = ["faceplan", "frame", "segments", "maxilla", "mandible", "chin", "skull", "translation",
        "rotation", "matrix", "axis", "angle_deg", "center", "euler_deg", "order", "cut_planes",
        "point", "normal", "from", "muscles", "mentalis", "model", "resolution", "sliding",
        "materials", "effects", "limits", "itk_transform"]
scalars = (st.none() | st.booleans() | st.integers(-10**30, 10**30)
           | st.floats(allow_nan=True, allow_infinity=True) | st.text(max_size=8) | st.sampled_from(KEYS))
trees = st.recursive(scalars, lambda kids: st.lists(kids, max_size=5)
                     | st.dictionaries(st.sampled_from(KEYS) | st.text(max_size=5) | st.integers(), kids, max_size=5),
                     max_leaves=30)


def _paths(tree, prefix=()):
    yield prefix
    if isinstance(tree, dict):
        for k, v in tree.items():
            yield from _paths(v, prefix + (k,))
    elif isinstance(tree, list):
        for i, v in enumerate(tree):
            yield from _paths(v, prefix + (i,))


ALL_PATHS = list(_paths(VALID))[1:]


def _outcome(call):
    try:
        plan = call()
    except InputError as exc:
        assert str(exc)
        return None
    for sp in plan.segments.values():
        r = sp.matrix[:3, :3]
        assert np.allclose(r.T @ r, np.eye(3), atol=1e-9) and abs(np.linalg.det(r) - 1) < 1e-9
    return plan


@settings(max_examples=150, deadline=None)
@given(trees)
def test_arbitrary_trees_never_crash(tree):
    _outcome(lambda: parse_plan(tree))


@settings(max_examples=200, deadline=None)
@given(st.sampled_from(ALL_PATHS), trees)
def test_mutated_valid_plan_never_crashes(path, value):
    data = copy.deepcopy(VALID)
    node = data
    for k in path[:-1]:
        node = node[k]
    node[path[-1]] = value
    _outcome(lambda: parse_plan(data))


@settings(max_examples=100, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.text(max_size=200) | st.sampled_from([yaml.safe_dump(VALID)[:n] for n in range(0, 600, 37)]))
def test_arbitrary_text_files_never_crash(tmp_path, text):
    p = tmp_path / "plan.yaml"
    p.write_text(text)
    _outcome(lambda: load_plan(p))


def test_the_valid_plan_is_valid():
    assert set(parse_plan(VALID).motions()) == {"maxilla", "mandible", "chin"}
