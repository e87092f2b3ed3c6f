"""Artifact I/O: nothing half-written ever replaces a good file (every stage and model writes through it)."""

from __future__ import annotations

import contextlib
import errno
import os
import tempfile
from pathlib import Path

import numpy as np


def _file_mode() -> int:
    """What ``open()`` would give a new file: 0666 less the process's umask."""
    umask = os.umask(0)
    os.umask(umask)
    return 0o666 & ~umask


_FILE_MODE = _file_mode()


@contextlib.contextmanager
def atomic_path(path):
    """Yield a temporary path beside ``path``; on success rename it over ``path``.

    If the body raises, the temporary file is removed and ``path`` is untouched.
    """
    path = Path(path)
    tmp = None
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
        os.close(fd)
        yield tmp
        os.chmod(tmp, _FILE_MODE)  # mkstemp's 0600 would make the artifact private
        os.replace(tmp, path)
    except OSError as e:
        if e.errno in WRITE_ERRORS:  # name the artifact, not its temporary (a full disk, a read-only one)
            raise OSError(e.errno, e.strerror, str(path)) from e
        raise
    finally:
        if tmp is not None and os.path.exists(tmp):
            os.remove(tmp)


# what a full or read-only disk raises: said plainly by `bcsdf` (exit 2), not as a traceback
WRITE_ERRORS = (errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EACCES, errno.EPERM)


def clear_torn(path) -> None:
    """Remove the temporaries :func:`atomic_path` left beside ``path`` when a process was
    killed (kill -9) between writing one and renaming it."""
    path = Path(path)
    for torn in path.parent.glob(f".{path.name}.*.tmp"):
        torn.unlink(missing_ok=True)


def write_text(path, text: str) -> None:
    with atomic_path(path) as tmp:
        Path(tmp).write_text(text)


def writable_folder(path) -> Path:
    """``path`` as a folder this process can write into (made if missing), checked before
    any long work; a ``ValueError`` that names it otherwise."""
    path = Path(path)
    for parent in (path, *path.parents):
        if parent.exists() and not parent.is_dir():
            raise ValueError(f"{parent} is a file, not a folder: give --artifacts a folder")
    try:
        path.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile(dir=path):
            pass
    except OSError as e:
        raise ValueError(f"cannot write into {path} ({e.strerror}): choose another --artifacts folder "
                         "or fix its permissions") from None
    return path


@contextlib.contextmanager
def exclusive(folder, what: str):
    """Hold ``folder``'s lock while ``what`` writes into it; refuse (``ValueError``) if
    another process holds it. Two runs of one config would write the same artifacts and
    interleave checkpoints. The lock is the kernel's (``flock``): it goes with the process,
    so a killed run leaves none behind."""
    import fcntl
    import time

    path = Path(folder) / ".lock"
    fh = open(path, "a+")
    try:
        try:
            fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            fh.seek(0)
            holder = fh.read().strip() or "another process"
            raise ValueError(f"{folder} is in use by {holder}: wait for it to finish (or stop it), or run with "
                             "--set name=... or another --artifacts folder") from None
        fh.seek(0)
        fh.truncate()
        fh.write(f"`{what}` (pid {os.getpid()}, since {time.strftime('%H:%M:%S')})")
        fh.flush()
        yield
    finally:
        fh.close()  # releases the lock


def check_axis(values, name: str, lo: float = -np.inf, hi: float = np.inf, span: float | None = None) -> None:
    """An axis read from an artifact: non-empty, finite, strictly increasing, within
    ``[lo, hi]`` and, if given, covering exactly ``span`` from first to last."""
    a = np.asarray(values, float)
    if a.ndim != 1 or a.size == 0 or not np.all(np.isfinite(a)):
        raise ValueError(f"axis {name}: must be a non-empty list of finite numbers")
    if np.any(np.diff(a) <= 0):
        raise ValueError(f"axis {name}: must increase strictly")
    if a[0] < lo - 1e-6 or a[-1] > hi + 1e-6:
        raise ValueError(f"axis {name}: must lie in [{lo:.6g}, {hi:.6g}] (got {a[0]:.6g} .. {a[-1]:.6g})")
    if span is not None and abs(a[-1] - a[0] - span) > 1e-6:
        raise ValueError(f"axis {name}: must cover {span:.6g} (got {a[-1] - a[0]:.6g})")
