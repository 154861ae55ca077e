# faceplan — the two commands of the README.
#   make demo : set up .venv (system packages too) and run the demo prediction into out/demo
#   make test : the same set-up, then the whole test suite
#   make portability : the suite under each BLAS / numba variant (bench/portability.sh)
.PHONY: setup demo test portability bench clean

setup:
	bash .ci/setup.sh

demo: setup
	.venv/bin/faceplan demo --out out/demo

# pytest exits 5 when it collects nothing: treat that as a failure to be visible, never silent.
test: setup
	.venv/bin/python -m pytest -q -n 2 tests

portability: setup
	bash bench/portability.sh

bench: setup
	for b in bench/*.py; do .venv/bin/python $$b || exit $$?; done

clean:
	rm -rf out .pytest_cache
