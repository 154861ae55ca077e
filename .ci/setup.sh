#!/usr/bin/env bash
# Idempotent set-up used by `make demo` and `make test`:
#  1. system packages that Python wheels cannot bring (CGAL/Eigen headers for pygalmesh,
#     Mesa for off-screen VTK rendering, Chromium for the report's browser test), installed
#     with apt-get only when missing;
#  2. a virtual environment in .venv with the project (editable) and every dependency.
# Re-running skips what is already there (a stamp file records the pyproject hash).
set -euo pipefail
cd "$(dirname "$0")/.."

SYS_PKGS="libcgal-dev libeigen3-dev libgmp-dev libmpfr-dev libegl1 libgl1 libosmesa6 libxrender1 chromium"
missing=""
for p in $SYS_PKGS; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing="$missing $p"
done
if [ -n "$missing" ]; then
  echo "[setup] installing system packages:$missing"
  SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends $missing
fi

PY=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then
  echo "[setup] creating .venv"
  "$PY" -m venv .venv
fi
stamp=.venv/.faceplan-installed
want=$(cat pyproject.toml | sha1sum | cut -d' ' -f1)
if [ ! -f "$stamp" ] || [ "$(cat "$stamp")" != "$want" ]; then
  echo "[setup] installing faceplan and its dependencies into .venv"
  .venv/bin/python -m pip install -q --upgrade pip wheel setuptools
  .venv/bin/python -m pip install -q -e ".[test,bench]"
  echo "$want" > "$stamp"
fi
.venv/bin/python -c "import solver, facemodel, generic_mesh, registration, planner" 
echo "[setup] ready: .venv/bin/faceplan"
