"""All-or-nothing output folders.

`atomic_output_dir(final)` yields a fresh temporary folder next to `final` (same file system, so
the final move is a `rename`). When the `with` block ends without an exception the temporary
folder replaces `final` (an existing `final` is first renamed aside, then removed, so a reader
never sees a half-written folder); when the block raises, the temporary folder is deleted and
`final` is left exactly as it was. This is how every faceplan command honours the contract's
"outputs appear whole or not at all".
"""
from __future__ import annotations

import contextlib
import os
import shutil
import tempfile
from pathlib import Path
from typing import Iterator

__all__ = ["atomic_output_dir", "atomic_write_file"]


@contextlib.contextmanager
def atomic_output_dir(final: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary sibling of `final`; move it into place only on success.

    Parent folders of `final` that did not exist are created, and removed again on failure if
    they are still empty, so a failed command leaves no trace.
    """
    final = Path(final).absolute()
    parent = final.parent
    created: list[Path] = []
    p = parent
    while not p.exists():
        created.append(p)
        p = p.parent
    parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{final.name}.tmp-", dir=parent))
    try:
        yield tmp
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        for d in created:  # innermost first
            with contextlib.suppress(OSError):
                d.rmdir()
        raise
    old = None
    if final.exists() or final.is_symlink():
        old = Path(tempfile.mkdtemp(prefix=f".{final.name}.old-", dir=parent))
        old.rmdir()
        os.replace(final, old)
    try:
        os.replace(tmp, final)
    except BaseException:
        if old is not None:
            os.replace(old, final)
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    os.chmod(final, 0o755 & ~_umask())
    if old is not None:
        if old.is_dir() and not old.is_symlink():
            shutil.rmtree(old, ignore_errors=True)
        else:
            old.unlink()


@contextlib.contextmanager
def atomic_write_file(final: str | os.PathLike, mode: str = "w") -> Iterator:
    """Open a temporary sibling of `final` for writing; rename it onto `final` on success."""
    final = Path(final).absolute()
    final.parent.mkdir(parents=True, exist_ok=True)
    fd, tmpname = tempfile.mkstemp(prefix=f".{final.name}.tmp-", dir=final.parent)
    tmp = Path(tmpname)
    try:
        with os.fdopen(fd, mode) as fh:
            yield fh
        os.chmod(tmp, 0o644 & ~_umask())
        os.replace(tmp, final)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
        raise


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask
