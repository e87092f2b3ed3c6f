"""Artifact I/O: nothing half-written ever replaces a good file (every stage and model writes through it)."""

from __future__ import annotations

import contextlib
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
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    os.close(fd)
    try:
        yield tmp
        os.chmod(tmp, _FILE_MODE)  # mkstemp's 0600 would make the artifact private
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.remove(tmp)


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
