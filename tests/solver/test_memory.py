"""`solver.memory.keep_freed_memory`: a large array freed and allocated again reuses the
process's pages instead of faulting fresh ones in.

Each child process allocates, fills and frees a 64 MB array ten times after a first one and
counts its minor page faults (getrusage). Returned to the kernel on every free, each array is a
fresh mapping whose pages fault in again: at least one fault per array (16,384 with 4 kB
pages, a few dozen where the kernel backs large arrays with 2 MB pages). Kept, the pages of the
first array serve the others: the bound, a quarter of the released count, says that most of
the faults are gone whatever the page size. Numbers are not touched: the filled sums are
checked.
"""
import subprocess
import sys

import pytest

CHILD = r"""
import resource, sys
import numpy as np
keep = sys.argv[1] == "keep"
if keep:
    from solver.memory import keep_freed_memory
    assert keep_freed_memory()
n = 64 * 2**20 // 8
a = np.ones(n); del a                       # the first allocation, outside the count
before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
total = 0.0
for k in range(10):
    a = np.full(n, float(k))
    total += a[::4096].sum()
    del a
print(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before, total)
"""


def _faults(mode):
    out = subprocess.run([sys.executable, "-c", CHILD, mode], capture_output=True, text=True,
                         check=True).stdout.split()
    return int(out[0]), float(out[1])


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's mallopt")
def test_freed_arrays_reuse_the_process_pages():
    from solver.memory import keep_freed_memory

    if not keep_freed_memory():
        pytest.skip("not glibc")
    released, s0 = _faults("release")
    kept, s1 = _faults("keep")
    assert s0 == s1 == 2048 * sum(range(10))
    assert released >= 10, released            # each fresh mapping faults in again
    assert kept < released / 4, (kept, released)
