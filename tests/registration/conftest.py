"""Shared fixtures: the coarse generic face model, and a registration cache private to the
test session (no test reads a result cached in ~/.cache by an earlier version of the code)."""
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))

import pytest


@pytest.fixture(scope="session", autouse=True)
def private_registration_cache(tmp_path_factory):
    """$FACEPLAN_CACHE points at a fresh directory for the whole session."""
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("FACEPLAN_CACHE", str(tmp_path_factory.mktemp("faceplan-cache")))
        yield


@pytest.fixture(scope="module")
def generic():
    """The coarse generic face model (the registration tests' template mesh)."""
    generic_mesh = pytest.importorskip("generic_mesh")
    return generic_mesh.load("coarse")
