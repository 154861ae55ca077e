"""All-or-nothing output folders that never destroy what the user already has.

`prepare_output(path, kind, inputs=...)` is the check every command runs on its `--out` before
any work: an output folder is only created new or replaced when it holds a previous faceplan
output of the same kind (the marker file `.faceplan-output.json`, written last, names the
command that made it). An existing file, a non-empty folder without the marker (or with
another command's marker), an input folder (the case) or any folder that contains one, the
working directory or one of its parents, the home folder and the file-system root are refused
with `InputError` (exit 2) naming the path. The nearest existing folder on the way to `path`
must be writable (a real probe file, not permission bits) and hold at least `min_free_mb` MB
(`check_free_space`, which a command calls again with an estimate once it knows its outputs' size).

`atomic_output_dir(final, kind)` yields a fresh hidden temporary folder next to `final` (same
file system, so the final move is a `rename`). When the `with` block ends without an exception
the marker is written into it last and the temporary folder replaces `final` (an existing
`final` is first renamed aside, then removed, so a reader never sees a half-written folder);
when the block raises, the temporary folder is deleted and `final` is left exactly as it was.
A run killed with SIGKILL leaves only hidden `.NAME.tmp-PID-*` / `.NAME.old-PID-*` folders;
the next run on the same `final` removes those whose process is gone (and puts a previous
output back if the kill fell between the two renames). This is how every faceplan command
honours the contract's "outputs appear whole or not at all".
"""
from __future__ import annotations

import contextlib
import errno
import json
import os
import shutil
import tempfile
import time
from pathlib import Path
from typing import Iterable, Iterator

from planner.errors import InputError

__all__ = ["MARKER", "MIN_FREE_MB", "check_free_space", "atomic_output_dir", "atomic_write_file", "check_output",
           "clean_orphans", "prepare_output"]

MARKER = ".faceplan-output.json"
# The free space required before a command has read anything: a floor, not an estimate, for
# the commands whose outputs (reports, a few meshes, pictures: ~10-40 MB) are not estimated.
# `faceplan predict` asks for its own floor here and checks an estimate of its outputs'
# size (`planner.output_size`) once the mesh is known, before the solve.
MIN_FREE_MB = 100.0
# Files that together identify an output written before the marker existed, by command: such a
# folder is accepted as a previous output of that command.
LEGACY_FILES = {
    "predict": ("prediction.vtu", "report.json"),
    "demo": ("prediction.vtu", "report.json", "case"),
    "register": ("patient_mesh.vtu", "report.json"),
    "compare": ("distances.vtp", "report.json"),
    "compare-summary": ("summary.json", "summary.csv"),
}


def _resolved(path: str | os.PathLike) -> Path:
    return Path(os.path.abspath(os.path.expanduser(os.fspath(path))))


def _is_within(inner: Path, outer: Path) -> bool:
    """inner == outer or inner lies inside outer (both resolved)."""
    try:
        inner.relative_to(outer)
        return True
    except ValueError:
        return False


def _marker_kind(folder: Path) -> str | None:
    """The command named by `folder`'s marker, '' for an unreadable marker, None without one."""
    m = folder / MARKER
    if not m.is_file():
        return None
    try:
        data = json.loads(m.read_text())
        return str(data.get("command", "")) if isinstance(data, dict) else ""
    except (OSError, ValueError):
        return ""


def check_output(path: str | os.PathLike, kind: str | None, inputs: Iterable = (),
                 legacy_files: Iterable[str] | None = None) -> Path:
    """Refuse an output location that would destroy something (InputError naming it).

    kind: the command name written in the marker; None checks only the rules that hold for
    every output (not a file, not an input, not the working directory or one of its parents,
    not home or the root) and leaves the folder's content to the caller. legacy_files: file
    names that together mark an output of this kind written before markers existed (a folder
    holding all of them is accepted as one; default `LEGACY_FILES[kind]`). Returns the absolute path."""
    out = _resolved(path)
    shown = os.fspath(path)
    real = Path(os.path.realpath(out))

    def refuse(why: str):
        raise InputError(f"--out {why}; nothing was written or changed", file=shown, field="--out")

    if real == Path(real.anchor) or real == Path(os.path.realpath(Path.home())):
        refuse("is the home folder or the file-system root")
    cwd = Path(os.path.realpath(os.getcwd()))
    if _is_within(cwd, real):
        refuse("is the working directory or one of its parents")
    for src in inputs:
        if src is None:
            continue
        s = Path(os.path.realpath(_resolved(src)))
        if _is_within(s, real):
            refuse(f"is {'the input' if s == real else 'a parent of the input'} {os.fspath(src)} "
                   "(it would be replaced)")
    if out.is_symlink() and not out.is_dir():
        refuse("is a symbolic link")
    if out.exists() and not out.is_dir():
        refuse("is an existing file, not an output folder")
    if kind is None or not out.is_dir():
        return out
    try:
        content = [p.name for p in out.iterdir()]
    except OSError as exc:
        refuse(f"cannot be read ({exc.strerror})")
    if not content:
        return out
    found = _marker_kind(out)
    legacy_files = LEGACY_FILES.get(kind, ()) if legacy_files is None else tuple(legacy_files)
    if found == kind:
        return out
    if found is None and legacy_files and set(legacy_files) <= set(content):
        return out
    if found:
        refuse(f"holds the output of `faceplan {found}`, not of `faceplan {kind}`: choose another folder")
    refuse(f"is a folder that is not empty and not a previous `faceplan {kind}` output "
           f"(no {MARKER} marker): choose a new or empty folder")


def _nearest_existing(path: Path) -> Path:
    p = path
    while not p.exists():
        p = p.parent
    return p


def _probe_writable(folder: Path) -> None:
    """Create and remove a file in `folder`: raises OSError when that is impossible."""
    fd, name = tempfile.mkstemp(prefix=".faceplan-probe-", dir=folder)
    os.close(fd)
    os.unlink(name)


def prepare_output(path: str | os.PathLike, kind: str, *, inputs: Iterable = (),
                   min_free_mb: float = MIN_FREE_MB, legacy_files: Iterable[str] | None = None) -> Path:
    """Check `path` as an output folder of command `kind` before any work; return it absolute.

    Every command calls this on its `--out` (or default output folder) right after reading its
    arguments, e.g. `out = prepare_output(args.out or case / "predict", "predict", inputs=[case])`,
    then writes with `atomic_output_dir(out, kind="predict", inputs=[case])`.
    Refused with InputError (exit 2, file = the path, field = --out), before anything is
    computed or written: an existing file; a non-empty folder that is not a previous output of
    `kind` (marker `.faceplan-output.json`); an input (`inputs`, e.g. the case folder) or a
    parent of one; the working directory or a parent of it; home; the root; a location whose
    nearest existing folder cannot be written to or has less than `min_free_mb` MB free."""
    out = check_output(path, kind, inputs, legacy_files)
    base = _nearest_existing(out.parent if not out.exists() else out)
    if not base.is_dir():
        raise InputError(f"--out: {base} is a file, a folder cannot be made under it",
                         file=os.fspath(path), field="--out")
    try:
        _probe_writable(base)
    except OSError as exc:
        raise InputError(f"--out is not writable ({base}: {exc.strerror or exc}); nothing was written",
                         file=os.fspath(path), field="--out") from exc
    check_free_space(out, min_free_mb, shown=path)
    return out


def check_free_space(path: str | os.PathLike, need_mb: float, *, what: str = "",
                     shown: str | os.PathLike | None = None) -> None:
    """Refuse (InputError, field --out) an output location whose disk has less than `need_mb`
    MB free; `what` says what needs the space (e.g. an estimate of the outputs' size), `shown`
    is the path named in the message (default `path`)."""
    out = Path(path)
    base = _nearest_existing(out.parent if not out.exists() else out)
    free_mb = shutil.disk_usage(base).free / 2**20
    if free_mb < need_mb:
        raise InputError(f"--out: only {free_mb:.0f} MB free on the disk of {base}, at least "
                         f"{need_mb:.0f} MB needed{f' ({what})' if what else ''}; nothing was written",
                         file=os.fspath(shown if shown is not None else path), field="--out")


def _pid_alive(pid: int) -> bool:
    if pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _orphan_pid(name: str, prefix: str) -> int | None:
    """PID encoded in a temporary name `prefix + PID-...`, None if it has none."""
    rest = name[len(prefix):]
    head = rest.split("-", 1)[0]
    return int(head) if head.isdigit() else None


def clean_orphans(final: str | os.PathLike, started: float | None = None) -> list[Path]:
    """Remove the hidden temporary siblings of `final` left by killed runs; return them.

    An orphan is a `.NAME.tmp-PID-*` or `.NAME.old-PID-*` entry whose process no longer runs
    (or, for names without a PID, older than `started`, default now minus one hour). When
    `final` is missing and an orphaned `.old-` folder exists, the kill fell between moving the
    previous output aside and moving the new one in: the previous output is put back."""
    final = _resolved(final)
    parent = final.parent
    if not parent.is_dir():
        return []
    started = time.time() - 3600.0 if started is None else started
    removed = []
    for kind in ("old", "tmp"):
        prefix = f".{final.name}.{kind}-"
        try:
            entries = [p for p in parent.iterdir() if p.name.startswith(prefix)]
        except OSError:
            return removed
        for p in sorted(entries):
            pid = _orphan_pid(p.name, prefix)
            try:
                dead = (not _pid_alive(pid)) if pid is not None else p.lstat().st_mtime < started
            except OSError:
                continue
            if not dead or pid == os.getpid():
                continue
            if kind == "old" and not final.exists() and p.is_dir():
                with contextlib.suppress(OSError):
                    os.replace(p, final)
                    continue
            if p.is_dir() and not p.is_symlink():
                shutil.rmtree(p, ignore_errors=True)
            else:
                with contextlib.suppress(OSError):
                    p.unlink()
            removed.append(p)
    return removed


def _write_marker(folder: Path, kind: str | None) -> None:
    record = {"faceplan_output": 1, "command": kind, "written_utc": time.strftime(
        "%Y-%m-%dT%H:%M:%SZ", time.gmtime()), "pid": os.getpid()}
    with open(folder / MARKER, "w") as fh:
        json.dump(record, fh)
        fh.flush()
        os.fsync(fh.fileno())


@contextlib.contextmanager
def atomic_output_dir(final: str | os.PathLike, kind: str | None = None, *,
                      inputs: Iterable = (), legacy_files: Iterable[str] | None = None) -> Iterator[Path]:
    """Yield a temporary sibling of `final`; move it into place only on success.

    kind: the command name; the folder is checked with `check_output` (before and again just
    before the move, so nothing that appeared meanwhile is lost) and receives the marker last.
    Without `kind` only the rules common to every output are checked and no marker is written.
    Parent folders of `final` that did not exist are created, and removed again on failure if
    they are still empty, so a failed command leaves no trace."""
    inputs = list(inputs)
    shown = final
    final = check_output(final, kind, inputs, legacy_files)
    parent = final.parent
    created: list[Path] = []
    p = parent
    while not p.exists():
        created.append(p)
        p = p.parent
    parent.mkdir(parents=True, exist_ok=True)
    clean_orphans(final)
    tmp = Path(tempfile.mkdtemp(prefix=f".{final.name}.tmp-{os.getpid()}-", dir=parent))

    def discard():
        shutil.rmtree(tmp, ignore_errors=True)
        for d in created:  # innermost first
            with contextlib.suppress(OSError):
                d.rmdir()

    try:
        yield tmp
        if kind is not None:
            _write_marker(tmp, kind)
        check_output(shown, kind, inputs, legacy_files)
    except BaseException:
        discard()
        raise
    old = None
    if final.exists() or final.is_symlink():
        old = Path(tempfile.mkdtemp(prefix=f".{final.name}.old-{os.getpid()}-", dir=parent))
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
    """Open a temporary sibling of `final` for writing; rename it onto `final` on success.

    An existing folder at `final` is refused (InputError), never replaced."""
    final = Path(final).absolute()
    if final.is_dir():
        raise InputError("is an existing folder, a file cannot replace it; nothing was written",
                         file=str(final), field="output file")
    final.parent.mkdir(parents=True, exist_ok=True)
    clean_orphans(final)
    fd, tmpname = tempfile.mkstemp(prefix=f".{final.name}.tmp-{os.getpid()}-", dir=final.parent)
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


def is_environment_error(exc: BaseException) -> bool:
    """An OSError that comes from the machine, not from faceplan: disk full, quota, read-only
    or failing file system, permission denied."""
    return isinstance(exc, OSError) and exc.errno in (
        errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EACCES, errno.EPERM, errno.EIO, errno.EFBIG)


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask
