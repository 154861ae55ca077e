"""generic_mesh package."""
