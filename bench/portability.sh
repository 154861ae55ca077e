#!/usr/bin/env bash
# The test suite under each BLAS / compiler variant a user's machine may pick: OpenBLAS's
# kernels for other processors (each rounds its sums in another order), MKL's conditional
# numerical reproducibility mode (PARDISO's kernels), numba compiled for a generic x86-64
# (no AVX-512/FMA). The suite must pass under every one: its tests assert properties of the
# results with tolerances that hold on any IEEE-754 machine (docs/portability.md).
#
#   bench/portability.sh            the whole suite (`make test`'s command) per variant
#   bench/portability.sh --quick    tests/registration and tests/solver only
#   bench/portability.sh --only NAME[,NAME...]   some variants (names as printed)
#
# Variants: default; OPENBLAS_CORETYPE=Haswell, SkylakeX, Sandybridge; MKL_CBWR=COMPATIBLE;
# NUMBA_CPU_NAME=generic; Sandybridge+generic (the combination .ci/run uses).
#
# One line per variant: `variant: pass|fail (N passed, M failed, T s)`; exit 1 if any failed.
# PYTHON (default .venv/bin/python) and WORKERS (default 2) may be set in the environment.
set -uo pipefail
cd "$(dirname "$0")/.."

PY=${PYTHON:-.venv/bin/python}
WORKERS=${WORKERS:-2}
TESTS=(tests)
ONLY=""
while [ $# -gt 0 ]; do
  case $1 in
    --quick) TESTS=(tests/registration tests/solver) ;;
    --only) ONLY=$2; shift ;;
    -h|--help) sed -n '2,16p' "$0"; exit 0 ;;
    *) echo "unknown option: $1" >&2; exit 2 ;;
  esac
  shift
done

# numba caches machine code per CPU name: a generic build must not share the default cache
GENERIC_CACHE=${TMPDIR:-/tmp}/faceplan-numba-generic
VARIANTS=(
  "default|"
  "OPENBLAS_CORETYPE=Haswell|OPENBLAS_CORETYPE=Haswell"
  "OPENBLAS_CORETYPE=SkylakeX|OPENBLAS_CORETYPE=SkylakeX"
  "OPENBLAS_CORETYPE=Sandybridge|OPENBLAS_CORETYPE=Sandybridge"
  "MKL_CBWR=COMPATIBLE|MKL_CBWR=COMPATIBLE"
  "NUMBA_CPU_NAME=generic|NUMBA_CPU_NAME=generic NUMBA_CACHE_DIR=$GENERIC_CACHE"
  # the combination .ci/run repeats the registration and solver tests under
  "Sandybridge+generic|OPENBLAS_CORETYPE=Sandybridge NUMBA_CPU_NAME=generic NUMBA_CACHE_DIR=$GENERIC_CACHE"
)

# each variant's pytest output is kept (for the failures' messages), removed when all passed
log_dir=$(mktemp -d "${TMPDIR:-/tmp}/faceplan-portability-XXXXXX")
status=0
for v in "${VARIANTS[@]}"; do
  name=${v%%|*}
  vars=${v#*|}
  if [ -n "$ONLY" ] && [[ ",$ONLY," != *",$name,"* ]]; then
    continue
  fi
  log="$log_dir/$(tr -c 'A-Za-z0-9=+\n' _ <<<"$name").log"
  start=$(date +%s.%N)
  # shellcheck disable=SC2086  # vars is a list of NAME=VALUE words
  env $vars "$PY" -m pytest -q -rfE -p no:cacheprovider -n "$WORKERS" "${TESTS[@]}" >"$log" 2>&1
  rc=$?
  secs=$(awk -v a="$start" -v b="$(date +%s.%N)" 'BEGIN { printf "%.0f", b - a }')
  summary=$(grep -E '^=* ?[0-9]+ (passed|failed|error)|no tests ran' "$log" | tail -1)
  passed=$(grep -oE '[0-9]+ passed' <<<"$summary" | awk '{ s += $1 } END { print s + 0 }')
  failed=$(grep -oE '[0-9]+ (failed|errors?)' <<<"$summary" | awk '{ s += $1 } END { print s + 0 }')
  # exit 0 with tests run is a pass; 5 (nothing collected) or anything else is a failure
  if [ "$rc" -eq 0 ] && [ "$passed" -gt 0 ]; then
    verdict=pass
  else
    verdict=fail
    status=1
  fi
  note=""
  [ "$rc" -eq 5 ] && note=", no tests ran"
  echo "$name: $verdict ($passed passed, $failed failed, $secs s$note)"
  if [ "$verdict" = fail ]; then
    grep -E '^(FAILED|ERROR) ' "$log" | sed 's/^/    /'
    echo "    log: $log"
  fi
done
[ "$status" -eq 0 ] && rm -rf "$log_dir"
exit $status
