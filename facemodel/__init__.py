"""facemodel package."""
