"""Keep the memory of large freed arrays in the process (`keep_freed_memory`).

A Newton iteration at 10^5 unknowns allocates arrays of tens of MB and frees them again: the
tangent's values on its pattern (8 bytes per stored entry), their aligned copy for the sparse
factorisation, the fourth-order material tangents of the elements outside the fused kernel.
glibc serves an allocation above its mmap threshold (128 kB to 32 MB, adaptive) by a fresh
mapping and returns it to the kernel on free, so every iteration faults the same amount of
memory in again, page by page, and the kernel zeroes each page. On a virtual machine that
reports freed guest pages to its host (free page reporting, memory ballooning) each such fault
is also a fault on the host, and the faults can cost more than the arithmetic that fills the
array.

`keep_freed_memory` asks glibc's allocator (mallopt(3)) to serve every allocation from its heap
(M_MMAP_MAX = 0) and to keep freed memory at the top of the heap rather than trim it
(M_TRIM_THRESHOLD at its largest value, M_TOP_PAD 64 MB): the next iteration's arrays reuse
pages already mapped. The process then keeps its peak heap until it exits, which is what a
solve's process wants (each solve of a run reaches about the same peak again). It is a
process-wide setting of the C allocator, numbers unchanged; `newton_solve` makes it once per
process. Where the C library is not glibc it does nothing.
"""
from __future__ import annotations

import ctypes
import ctypes.util
import logging
import sys

__all__ = ["keep_freed_memory"]

log = logging.getLogger("solver.memory")

# mallopt(3) parameter numbers (glibc's malloc.h)
_M_TRIM_THRESHOLD, _M_TOP_PAD, _M_MMAP_MAX = -1, -2, -4
_TOP_PAD_BYTES = 64 << 20
_INT_MAX = 2 ** 31 - 1

# False: `keep_freed_memory` leaves the allocator as it is (a benchmark's peer run sets it
# before the first solve)
KEEP_FREED_MEMORY = True

_state = {"done": False, "kept": False}


def keep_freed_memory() -> bool:
    """Make glibc keep freed memory in the process (module text); once per process, unless
    `KEEP_FREED_MEMORY` is False. True when the setting is in force (glibc accepted it), False
    otherwise."""
    if _state["done"]:
        return _state["kept"]
    if not KEEP_FREED_MEMORY:
        return False
    _state["done"] = True
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
        libc.gnu_get_libc_version          # glibc only: musl and others have no such entry
    except (OSError, AttributeError):
        return False
    mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
    mallopt.restype = ctypes.c_int
    ok = all(mallopt(p, v) == 1 for p, v in ((_M_MMAP_MAX, 0), (_M_TRIM_THRESHOLD, _INT_MAX),
                                             (_M_TOP_PAD, _TOP_PAD_BYTES)))
    if not ok:
        log.debug("mallopt refused a setting: freed memory goes back to the kernel as before")
    _state["kept"] = ok
    return ok
