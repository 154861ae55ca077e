"""`simulate` refuses input it cannot use with `ModelInputError` (a ValueError, so callers
that catch ValueError keep working) and never drops a model part silently: contact asked of a
model without lip contact surfaces is refused before any solve."""
import dataclasses

import pytest

import generic_mesh
from facemodel.errors import ModelInputError
from facemodel.simulation import simulate


@pytest.fixture(scope="module")
def face():
    return generic_mesh.load("coarse")


def test_bad_input_is_a_model_input_error(face):
    with pytest.raises(ModelInputError, match="unknown muscle"):
        simulate(face, {}, {"tongue": 0.2})
    assert issubclass(ModelInputError, ValueError)


def test_contact_without_lip_surfaces_is_refused(face):
    sets = {k: v for k, v in face.facet_sets.items() if k != "lip_lower_contact"}
    no_lips = dataclasses.replace(face, facet_sets=sets)
    with pytest.raises(ModelInputError, match="lip_lower_contact"):
        simulate(no_lips, {}, {"orbicularis_oris": 0.05}, contact=True)
