"""Shared fixtures: the analytic shell stands in for the generic face model (see shell.py)."""
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))

import pytest


@pytest.fixture(scope="module")
def generic():
    """The coarse generic face model (the registration tests' template mesh)."""
    generic_mesh = pytest.importorskip("generic_mesh")
    return generic_mesh.load("coarse")
