"""Output directories filled all at once, by one run at a time.

:func:`output_set` is the context in which a command writes its set of result files:

* **One run at a time.**  It takes an exclusive lock (``fcntl.flock``) on a lock file next
  to the output directory (``.NAME.reblur-lock`` in its parent), so a second run into the
  same directory is refused at once with :class:`OutputDirError`.  The kernel releases the
  lock when its process dies, however it dies; the file itself is removed at the end.
* **All or nothing.**  Every file is written into a temporary sibling directory
  (``.NAME.reblur-tmp-PID-XXXXXX``) that is renamed onto the output directory when the block
  ends without error.  An existing output directory holding only earlier results (with
  ``overwrite``) or nothing is first renamed aside (``.NAME.reblur-old-PID-XXXXXX``) and
  deleted after the rename.  "Earlier results" are the files the earlier run's manifest
  (``report.json``) lists: with ``--overwrite`` those this run does not rewrite are removed
  (say, the ``changes.tif`` of an earlier, larger input), while a file that merely has a
  result's name but is not listed is left where it is, with a warning.  An error (a full
  disk, an interrupt) removes the temporary directory and leaves the output directory as it
  was.  When the output directory also holds
  other files (an input, notes of the user's), it cannot be replaced: the finished files are
  then moved into it one by one, the report last and the earlier report removed first, so
  the window in which a reader could see a mixed set is a few renames long.
* **Stale temporaries** of a process that is no longer alive (killed during the write) are
  deleted by the next run into the same directory.

When the parent directory is not writable (or is on another file system than the output
directory) the temporary directory and the lock go inside the output directory instead.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import logging
import os
import re
import shutil
import stat
import tempfile
from collections.abc import Iterator, Sequence
from pathlib import Path

from .io import display_path

__all__ = ["OutputDirError", "output_set", "lock_path", "remove_stale"]

log = logging.getLogger(__name__)

_TMP = "reblur-tmp"
_OLD = "reblur-old"
_LOCK = "reblur-lock"


class OutputDirError(ValueError):
    """The output directory cannot be used now; the message is one line naming it."""


def _in_parent(out: Path) -> bool:
    """Whether temporaries and the lock can live next to ``out`` (else: inside it)."""
    parent = out.parent
    if not os.access(parent, os.W_OK | os.X_OK):
        return False
    if out.exists():
        return os.stat(out).st_dev == os.stat(parent).st_dev and out != parent
    return True


def lock_path(out: str | os.PathLike) -> Path:
    """The lock file :func:`output_set` holds while writing into ``out``.

    ``.NAME.reblur-lock`` in the parent of ``out``, or ``.reblur-lock`` inside ``out``
    when the parent is not writable.
    """
    out = Path(os.path.abspath(out))
    return out.parent / f".{out.name}.{_LOCK}" if _in_parent(out) else out / f".{_LOCK}"


def _pid_alive(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def remove_stale(out: str | os.PathLike) -> list[Path]:
    """Delete temporaries that runs into ``out`` left when killed; return what was removed.

    Temporary and set-aside directories (``.NAME.reblur-tmp-PID-*``, ``.NAME.reblur-old-PID-*``
    next to ``out``, ``.reblur-tmp-PID-*`` and ``.reblur-work-PID`` inside it) whose process
    ``PID`` is no longer alive are removed.  Call it holding the lock of ``out``.
    """
    out = Path(os.path.abspath(out))
    pats = [(out.parent, re.compile(rf"\.{re.escape(out.name)}\.(?:{_TMP}|{_OLD})-(\d+)-"))]
    if out.is_dir():
        pats.append((out, re.compile(rf"\.(?:{_TMP}-(\d+)-|reblur-work-(\d+)$)")))
    removed = []
    for where, pat in pats:
        try:
            entries = list(where.iterdir())
        except OSError:
            continue
        for p in entries:
            m = pat.match(p.name)
            if m is None:
                continue
            pid = int(next(g for g in m.groups() if g is not None))
            if _pid_alive(pid):
                continue
            if p.is_dir() and not p.is_symlink():
                shutil.rmtree(p, ignore_errors=True)
            else:
                with contextlib.suppress(OSError):
                    p.unlink()
            if not p.exists():
                removed.append(p)
                log.info("removed %s, left by a run that was stopped (pid %d)", p, pid)
    return removed


@contextlib.contextmanager
def _locked(out: Path, path: Path) -> Iterator[None]:
    """Hold an exclusive ``flock`` on ``path``; refuse at once when another process does."""
    while True:
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o666)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as exc:
            os.close(fd)
            if exc.errno not in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
                raise
            try:
                holder = path.read_text().strip()
            except OSError:
                holder = ""
            who = f" (pid {holder})" if holder.isdigit() else ""
            raise OutputDirError(
                f"{display_path(out)}: another reblur run{who} is writing into this output "
                "directory; wait for it to finish or choose another --out"
            ) from None
        # the holder before us may have removed the file after we opened it: lock the new one
        try:
            same = os.fstat(fd).st_ino == os.stat(path).st_ino
        except FileNotFoundError:
            same = False
        if same:
            break
        os.close(fd)
    try:
        os.ftruncate(fd, 0)
        os.write(fd, f"{os.getpid()}\n".encode())
        yield
    finally:
        with contextlib.suppress(OSError):
            path.unlink()
        os.close(fd)


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def _earlier_set(out: Path, names: Sequence[str], manifest: str | None) -> set[str]:
    """The files of ``names`` in ``out`` that belong to an earlier result set.

    Without a ``manifest`` every one of them does.  With one (``report.json``, whose
    ``files`` lists the set it completes), only the manifest and the files it lists: a
    ``changes.tif`` the earlier report does not name is someone else's file, not a result
    to delete.  No readable manifest: none.
    """
    present = {n for n in names if (out / n).exists() or (out / n).is_symlink()}
    if manifest is None:
        return present
    try:
        import json

        files = json.loads((out / manifest).read_text(encoding="utf-8")).get("files")
    except (OSError, ValueError, AttributeError):
        return set()
    listed = files.values() if isinstance(files, dict) else files
    if not isinstance(listed, (list, type({}.values()))):
        return set()
    # a folder of the set (viewer/) is listed by a file in it (viewer/index.html)
    return present & ({manifest} | {str(n).split("/")[0] for n in listed})


def _plan(out: Path, stage: Path, names: Sequence[str],
          manifest: str | None) -> tuple[set[str], set[str], set[str]]:
    """``(new, stale, kept)``: the files this run writes; earlier results it does not write
    (removed); files of ``names`` that are neither (left in place, with a warning)."""
    new = {p.name for p in stage.iterdir()}
    present = {n for n in names if (out / n).exists() or (out / n).is_symlink()}
    owned = _earlier_set(out, names, manifest)
    stale = owned - new
    kept = present - owned - new
    for n in sorted(stale):
        log.warning("removed %s: a file of the earlier result set that this run does not "
                    "write", display_path(out / n))
    for n in sorted(kept):
        log.warning("left %s in place: this run does not write it and the earlier report "
                    "does not list it (it is not part of the new result set)",
                    display_path(out / n))
    return new, stale, kept


def _move_in(stage: Path, out: Path, new: set[str], stale: set[str],
             last: Sequence[str]) -> None:
    """Move the files of ``stage`` into the existing ``out`` one by one: ``last`` (the
    report) is removed first and moved in last, the ``stale`` results are removed."""
    gone = [n for n in last if (out / n).exists() or (out / n).is_symlink()]
    for n in gone + sorted(stale - set(gone)):
        _remove(out / n)
    for n in sorted(new, key=lambda n: (n in last, list(last).index(n) if n in last else 0)):
        if (stage / n).is_dir() and (out / n).is_dir() and not (out / n).is_symlink():
            _remove(out / n)  # a folder of results (viewer/) replaces the earlier one
        os.replace(stage / n, out / n)


def _remove(p: Path) -> None:
    """Delete a result file or folder (a missing one is fine)."""
    if p.is_dir() and not p.is_symlink():
        shutil.rmtree(p)
    else:
        with contextlib.suppress(FileNotFoundError):
            p.unlink()


def _commit(stage: Path, out: Path, names: Sequence[str], last: Sequence[str],
            sibling: bool, manifest: str | None) -> None:
    if not out.exists():
        os.chmod(stage, 0o777 & ~_umask())
        os.rename(stage, out)
        return
    new, stale, kept = _plan(out, stage, names, manifest)
    entries = [p.name for p in out.iterdir()]
    if not sibling or kept or any(n not in names for n in entries):
        _move_in(stage, out, new, stale, last)
        stage.rmdir()
        return
    # only this run's results and the earlier set's (or nothing): swap the whole directory
    os.chmod(stage, stat.S_IMODE(os.stat(out).st_mode))
    aside = Path(tempfile.mkdtemp(prefix=f".{out.name}.{_OLD}-{os.getpid()}-", dir=out.parent))
    os.rename(out, aside / "old")
    os.rename(stage, out)
    shutil.rmtree(aside, ignore_errors=True)


@contextlib.contextmanager
def output_set(
    out: str | os.PathLike,
    names: Sequence[str],
    *,
    overwrite: bool = False,
    last: Sequence[str] = (),
    manifest: str | None = None,
) -> Iterator[Path]:
    """Write a set of result files into ``out`` all at once, one run at a time.

    Parameters
    ----------
    out : str or path-like
        The output directory (created, with missing parents, when the block succeeds).
    names : sequence of str
        Every file name a run may write into ``out``: earlier files of these names are
        "results" (refused without ``overwrite``, replaced with it, removed when the new
        set does not hold them); other files in ``out`` are left alone.
    overwrite : bool
        Replace earlier results.
    last : sequence of str
        Files moved in last (and removed first) when ``out`` must be filled file by file:
        the report that tells a reader the set is complete.
    manifest : str, optional
        The file of ``names`` that lists the files of its set (``report.json``, key
        ``files``).  With ``overwrite``, only the earlier manifest and the files it lists are
        removed when this run does not rewrite them; a file of ``names`` it does not list (a
        ``changes.tif`` of the user's, or of another tool) is left in place, with a warning.
        Default: every file of ``names`` belongs to the earlier set.

    Yields
    ------
    Path
        The temporary directory to write every file into (same names as in ``out``).

    Raises
    ------
    OutputDirError
        Another run holds the lock of ``out``, or ``out`` holds results and not
        ``overwrite``.
    """
    out = Path(os.path.abspath(out))
    created = []
    anc = out.parent
    while not anc.exists():
        created.append(anc)
        anc = anc.parent
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        sibling = _in_parent(out)
        with _locked(out, lock_path(out)):
            remove_stale(out)
            found = [n for n in names if (out / n).exists()]
            if found and not overwrite:
                raise OutputDirError(
                    f"{display_path(out)}: already holds results ({', '.join(found[:3])}"
                    f"{', ...' if len(found) > 3 else ''}); use --overwrite to replace them"
                )
            where, prefix = ((out.parent, f".{out.name}.{_TMP}-{os.getpid()}-") if sibling
                             else (out, f".{_TMP}-{os.getpid()}-"))
            stage = Path(tempfile.mkdtemp(prefix=prefix, dir=where))
            try:
                yield stage
                _commit(stage, out, names, last, sibling, manifest)
            except BaseException:
                shutil.rmtree(stage, ignore_errors=True)
                raise
    finally:
        for d in created:  # deepest first; only those still empty (a failed run)
            with contextlib.suppress(OSError):
                d.rmdir()
