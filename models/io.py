"""Artifact I/O: nothing half-written ever replaces a good file (every stage and model writes through it).

Three guarantees, each one mechanism here:

* **atomic files**: :func:`atomic_path` writes a temporary beside the artifact and renames
  it over the artifact only when the write finished;
* **nothing outside the root**: under :func:`confined` every write (and the lock) is
  refused unless its folder, links resolved, lies inside the artifacts root; a link in
  the tree that points out of it is named;
* **all-or-nothing stages**: under :func:`journal` every file a stage replaces is kept
  until the stage finishes; a stage that fails (or a process killed mid-stage, at the
  next command) is rolled back, so the earlier set of artifacts stays whole.
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

import numpy as np


def _file_mode() -> int:
    """What ``open()`` would give a new file: 0666 less the process's umask."""
    umask = os.umask(0)
    os.umask(umask)
    return 0o666 & ~umask


_FILE_MODE = _file_mode()
_ROOT: list = []      # the confining root, while a command runs (see confined)
_JOURNAL: list = []   # the open journal, while a stage runs (see journal)


@contextlib.contextmanager
def confined(root):
    """Refuse every write outside ``root`` (links resolved) while the body runs."""
    _ROOT.append(Path(root).resolve())
    try:
        yield
    finally:
        _ROOT.pop()


@contextlib.contextmanager
def scratch(folder):
    """A stage's own temporary folder (the stability stage's small bakes): the body may write
    there, confined to it, outside any stage journal (scratch work is thrown away whole)."""
    saved = _JOURNAL[:]
    _JOURNAL.clear()
    _ROOT.append(Path(folder).resolve())
    try:
        yield
    finally:
        _ROOT.pop()
        _JOURNAL[:] = saved


def check_inside(path) -> Path:
    """``path`` if its folder, links resolved, lies inside the confining root; else a
    ``ValueError`` naming the link that leads out. Without a root, any path."""
    path = Path(path)
    if not _ROOT:
        return path
    root = _ROOT[-1]
    real = path.parent.resolve()
    if real != root and root not in real.parents:
        raise ValueError(f"refusing to write {path}: its folder leads to {real}, outside the artifacts root {root} "
                         "(a symbolic link in the artifacts tree?); remove the link")
    if path.is_symlink():
        target = path.resolve()
        if target != root and root not in target.parents:
            raise ValueError(f"refusing to write {path}: it is a link to {target}, outside the artifacts root "
                             f"{root}; remove the link")
    return path


@contextlib.contextmanager
def atomic_path(path, journaled: bool = True):
    """Yield a temporary path beside ``path``; on success rename it over ``path``.

    If the body raises, the temporary file is removed and ``path`` is untouched. Under a
    :func:`journal` the earlier file is kept until the stage finishes (``journaled=False``
    for what must outlive a failed stage: a bake's checkpoint).
    """
    path = check_inside(path)
    tmp = None
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        if _JOURNAL and journaled:  # recorded before anything is written, its temporary included
            _JOURNAL[-1].keep(path)
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


# what the disk or its limits raise (full, over quota, read-only, a file-size limit, a name
# too long): said plainly by `bcsdf` (exit 2), not as a traceback
WRITE_ERRORS = (errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EACCES, errno.EPERM, errno.EFBIG,
                errno.ENAMETOOLONG)
# something in the artifacts tree in the way: a folder where a file belongs, a file where a
# folder belongs, a link loop
OBSTACLES = (errno.EISDIR, errno.ENOTDIR, errno.ELOOP, errno.EEXIST, errno.ENOTEMPTY)


def clear_torn(path) -> None:
    """Remove the temporaries :func:`atomic_path` left beside ``path`` when a process was
    killed (kill -9) between writing one and renaming it."""
    path = Path(path)
    for torn in path.parent.glob(f".{path.name}.*.tmp"):
        torn.unlink(missing_ok=True)


class JournalError(ValueError):
    """A stage's undo could not finish; its journal is kept, and the next command on the
    config finishes it."""


def _fsync_folder(folder: Path) -> None:
    """Make a folder's new entries (a rename, a link) survive a power cut."""
    fd = os.open(folder, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


# a hard link cannot be made here (another filesystem, a filesystem without links): copy
_NO_LINK = (errno.EXDEV, errno.EPERM, errno.ENOTSUP, errno.EOPNOTSUPP, errno.EMLINK)


class _Journal:
    """What a stage replaced or created, on disk, so that a failed or killed stage can be
    undone; the most careful code in the project, because everything else trusts it.

    * **A record before the change.** Each file the stage will replace or create gets a
      record (``NNNNNN.json``: what, where, its backup), written whole (a temporary,
      synced, renamed) and synced before the file is touched: a record is complete or
      absent, and a change without a record cannot happen.
    * **Recorded before written.** :func:`atomic_path` records its file before it makes
      the temporary it writes, so an undo also removes a temporary a kill left behind.
    * **The earlier file beside itself.** A replaced file is kept as a hard link in its own
      folder (``.name.NNNNNN.undo``): the same filesystem whatever is mounted where (a
      copy where links cannot be made), so a stage folder on another disk is no obstacle.
    * **Undo and commit can be interrupted and run again.** Undo renames each backup over
      its file (a record whose backup is gone is done, or never began) and removes what
      was created; commit first writes a ``committed`` mark, then removes the backups.
      Whatever kills either, the next command finishes it; the journal folder goes last.
      Ctrl-C is held back while either runs (it takes a moment), then delivered.
    """

    def __init__(self, folder: Path):
        self.folder = folder
        self.seen: set = set()
        self.n = 0

    # -- records ---------------------------------------------------------------------
    def _record(self, **entry) -> None:
        self.n += 1
        rec = self.folder / f"{self.n:06d}.json"
        tmp = self.folder / f".{self.n:06d}.json.tmp"
        with open(tmp, "w") as fh:
            fh.write(json.dumps(entry))
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, rec)
        _fsync_folder(self.folder)

    def _records(self) -> list:
        out = []
        for rec in sorted(self.folder.glob("[0-9]*.json")):
            try:
                entry = json.loads(rec.read_text())
                if entry.get("kind") not in ("kept", "created") or not entry.get("target") or \
                        (entry["kind"] == "kept" and not entry.get("backup")):
                    raise ValueError("incomplete")
            except (OSError, ValueError) as e:
                raise JournalError(f"the stage journal record {rec} is unreadable ({e}); it was written whole, so "
                                   f"something else changed it: look at the files it names, then remove "
                                   f"{self.folder}") from None
            out.append(entry)
        return out

    # -- while the stage runs ------------------------------------------------------------
    def keep(self, path: Path) -> None:
        """Record ``path`` (and keep its earlier content) before the stage replaces it."""
        key = str(path.resolve())
        if key in self.seen:
            return
        self.seen.add(key)
        self.folder.mkdir(parents=True, exist_ok=True)
        if not (path.exists() and not path.is_symlink()):
            self._record(kind="created", target=key)
            return
        backup = path.parent / f".{path.name}.{self.n + 1:06d}.undo"
        self._record(kind="kept", target=key, backup=str(backup.resolve()))
        backup.unlink(missing_ok=True)   # a stale one of an earlier journal that never got this far
        try:
            os.link(path, backup)
        except OSError as e:
            if e.errno not in _NO_LINK:
                raise
            tmp = backup.with_name(backup.name + ".tmp")
            shutil.copy2(path, tmp)
            with open(tmp, "rb+") as fh:
                os.fsync(fh.fileno())
            os.replace(tmp, backup)
        _fsync_folder(path.parent)

    # -- the end: undo or commit -----------------------------------------------------------
    def roll_back(self) -> None:
        """Undo the stage (or, if it committed, finish the commit); idempotent."""
        if not self.folder.exists():
            return
        with _signals_held():
            try:
                if (self.folder / "committed").exists():
                    self._drop_backups()
                    self._clear()
                    return
                else:
                    for entry in self._records():
                        target = Path(entry["target"])
                        clear_torn(target)   # a temporary the killed stage was writing
                        if entry["kind"] == "created":
                            target.unlink(missing_ok=True)
                        elif os.path.lexists(entry["backup"]):
                            if target.exists() and os.path.samefile(entry["backup"], target):
                                os.unlink(entry["backup"])   # never replaced (rename would keep both links)
                            else:
                                os.replace(entry["backup"], target)
                            _fsync_folder(target.parent)
                shutil.rmtree(self.folder)
            except OSError as e:
                raise JournalError(f"could not undo the unfinished stage ({e}); its journal {self.folder} keeps "
                                   "what is needed: fix the cause and run any bcsdf command on this config again "
                                   "to finish the undo") from None

    def commit(self) -> None:
        """Keep the stage's files: mark the journal committed, then drop the backups."""
        with _signals_held():
            try:
                mark = self.folder / "committed"
                with open(mark, "w") as fh:
                    os.fsync(fh.fileno())
                _fsync_folder(self.folder)
                self._drop_backups()
                self._clear()
            except OSError as e:
                raise JournalError(f"the stage finished but its journal could not be closed ({e}); fix the "
                                   f"cause and run any bcsdf command on this config again") from None

    def _clear(self) -> None:
        """Remove the journal: the records first, the ``committed`` mark last (a kill
        between them must not turn a commit into an undo)."""
        for rec in self.folder.iterdir():
            if rec.name != "committed":
                rec.unlink()
        shutil.rmtree(self.folder)

    def _drop_backups(self) -> None:
        for entry in self._records():
            if entry["kind"] == "kept":
                Path(entry["backup"]).unlink(missing_ok=True)


@contextlib.contextmanager
def _signals_held():
    """Hold back SIGINT and SIGTERM while the body runs (they arrive after it): an undo or a
    commit takes a moment and is safer finished than interrupted. Main thread only."""
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread():
        yield
        return
    held = {signal.SIGINT, signal.SIGTERM}
    old = signal.pthread_sigmask(signal.SIG_BLOCK, held)
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, old)


@contextlib.contextmanager
def journal(folder):
    """Run a stage all or nothing: the files it writes under ``folder`` (``.journal`` there)
    are committed together when the body returns; if it raises, every file it replaced is
    restored and every file it created removed. A journal left by a killed process (or an
    interrupted undo or commit) is finished first."""
    j = _Journal(Path(folder) / ".journal")
    j.roll_back()  # a stage killed mid-way left this: undo it before anything else
    j.folder.mkdir(parents=True, exist_ok=True)
    _JOURNAL.append(j)
    try:
        yield
    except BaseException:
        _JOURNAL.remove(j)
        j.roll_back()
        raise
    else:
        _JOURNAL.remove(j)
        j.commit()


def write_text(path, text: str) -> None:
    with atomic_path(path) as tmp:
        Path(tmp).write_text(text)


def writable_folder(path) -> Path:
    """``path`` as a folder this process can write into (made if missing), checked before
    any long work; a ``ValueError`` that names it otherwise."""
    path = Path(path)
    check_inside(path / ".lock")  # the config's folder itself may be a link out of the root
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

    path = check_inside(Path(folder) / ".lock")
    try:  # never through a link: a planted link must not truncate the file it points at
        fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW, _FILE_MODE)
    except OSError as e:
        if e.errno == errno.ELOOP:
            raise ValueError(f"{path} is a symbolic link; remove it (the lock is a plain file)") from None
        raise
    fh = os.fdopen(fd, "r+")
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
