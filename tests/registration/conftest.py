"""Shared fixtures: the analytic shell stands in for the generic face model (see shell.py)."""
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))
