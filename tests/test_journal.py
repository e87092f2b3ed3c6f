"""The stage journal (``models.io.journal``) under the faults that bricked configs: a process
killed at every step of a stage, of its undo and of its commit; a full disk (a real, small
tmpfs); a stage folder on another filesystem. After each, the next command finds the earlier
set of artifacts whole (or the new one, if the stage had committed), never a mixture, and
no journal or backup left behind."""

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from models.io import JournalError, journal, write_text

OLD = {"fiber/table.npz": "old table", "fiber/summary.json": "old summary", "export/model.onnx": "old onnx"}
NEW = {"fiber/table.npz": "new table", "fiber/summary.json": "new summary", "export/model.onnx": "new onnx",
       "export/weights.npz": "new weights"}

# a stage in a child process: replaces three files, creates one, then succeeds or fails;
# the n-th call of a file-system primitive kills it (os._exit, as kill -9 would)
CHILD = textwrap.dedent("""
    import os, shutil, sys
    from pathlib import Path
    from models.io import journal, write_text

    folder, kill_at, fail = Path(sys.argv[1]), int(sys.argv[2]), sys.argv[3] == "fail"
    calls = [0]

    def counted(f):
        def g(*a, **k):
            calls[0] += 1
            if calls[0] == kill_at:
                os._exit(9)
            return f(*a, **k)
        return g

    for name in ("replace", "link", "fsync", "unlink", "rmdir", "mkdir"):
        setattr(os, name, counted(getattr(os, name)))
    new = {new!r}
    with journal(folder):
        for rel, text in new.items():
            write_text(folder / rel, text)
        if fail:
            raise SystemExit(3)
    print("calls", calls[0])
""").replace("{new!r}", repr(NEW))


def state(folder: Path) -> dict:
    """Every file under ``folder`` but the journal's and the lock: relative path -> text."""
    return {str(p.relative_to(folder)): p.read_text() for p in sorted(folder.rglob("*"))
            if p.is_file() and ".journal" not in p.parts}


def seed(folder: Path) -> None:
    for rel, text in OLD.items():
        write_text(folder / rel, text)


def run_child(folder, kill_at, fail):
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1])}
    return subprocess.run([sys.executable, "-c", CHILD, str(folder), str(kill_at), "fail" if fail else "ok"],
                          capture_output=True, text=True, env=env)


@pytest.mark.parametrize("fail", [False, True], ids=["stage and commit", "stage and undo"])
def test_a_process_killed_at_any_step_leaves_a_whole_set(tmp_path, fail):
    """Killed at the k-th file-system call, for every k until the child finishes: the next
    command (opening the journal) sees the old set or, once the commit began, the new one;
    the undo after a failure, killed anywhere, still ends in the old set."""
    k, seen = 1, set()
    while True:
        folder = tmp_path / f"k{k}"
        seed(folder)
        done = run_child(folder, k, fail)
        assert done.returncode in (9, 0, 3), done.stderr
        with journal(folder):   # the next command: finishes whatever the killed one left
            pass
        got = state(folder)
        assert got in (OLD, NEW), (k, got)
        assert not fail or got == OLD, (k, got)
        assert not (folder / ".journal").exists()
        seen.add("old" if got == OLD else "new")
        if done.returncode != 9:
            break
        k += 1
    assert k > 20                                   # every step of the stage was a kill point
    assert seen == ({"old"} if fail else {"old", "new"})


def test_an_unreadable_record_stops_the_undo_with_the_file_named(tmp_path):
    folder = tmp_path / "cfg"
    seed(folder)
    (folder / ".journal").mkdir()
    (folder / ".journal" / "000001.json").write_text("")   # not something the journal writes
    with pytest.raises(JournalError, match="000001.json is unreadable"):
        with journal(folder):
            pass
    assert state(folder) == OLD


@pytest.fixture
def tmpfs(tmp_path):
    """Mount a small tmpfs (root only: CI runs as root) and hand a factory for more."""
    if os.geteuid() != 0:
        pytest.skip("mounting a tmpfs needs root (CI runs as root)")
    mounted = []

    def mount(path: Path, size: str, inodes: int = 64) -> Path:
        path.mkdir(parents=True, exist_ok=True)
        done = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size},nr_inodes={inodes}", "tmpfs", str(path)],
                              capture_output=True, text=True)
        if done.returncode != 0:   # a container without CAP_SYS_ADMIN: said, not hidden
            pytest.skip(f"this machine refuses to mount a tmpfs ({done.stderr.strip()})")
        mounted.append(path)
        return path

    yield mount
    for path in reversed(mounted):
        subprocess.run(["umount", str(path)], check=False)


def fill(folder: Path, leave_bytes: int) -> None:
    """Fill the filesystem of ``folder`` but about ``leave_bytes``."""
    st = os.statvfs(folder)
    free = st.f_bavail * st.f_frsize
    if free > leave_bytes:
        with open(folder / "filler", "wb") as fh:
            try:
                fh.write(b"\0" * (free - leave_bytes))
            except OSError:
                pass


@pytest.mark.parametrize("leave", [0, 4096, 8192, 12288, 16384, 24576])
def test_a_full_disk_at_any_point_leaves_a_whole_set_and_a_live_config(tmpfs, tmp_path, leave):
    """On a full tmpfs, the disk runs out at a different write of the stage for each amount
    left free: the stage fails with the write named, the set stays whole, and once space is
    freed the same stage runs and commits."""
    disk = tmpfs(tmp_path / "disk", "256k")
    folder = disk / "cfg"
    seed(folder)
    fill(disk, leave)
    big = {**NEW, "export/weights.npz": "w" * 60_000}
    try:
        with journal(folder):
            for rel, text in big.items():
                write_text(folder / rel, text)
    except (OSError, JournalError) as e:
        print("failed:", e)
        assert "No space left" in str(e), e
        assert state(folder) == OLD
    else:
        assert state(folder) == big
    assert not list(folder.rglob("*.undo")) and not (folder / ".journal").exists()
    (disk / "filler").unlink(missing_ok=True)
    with journal(folder):                           # the config lives on
        for rel, text in NEW.items():
            write_text(folder / rel, text)
    assert state(folder) == NEW and not (folder / ".journal").exists()


def test_a_stage_folder_on_another_filesystem_is_journaled(tmpfs, tmp_path):
    """A bigger disk mounted at a stage folder: the journal (in the config folder) keeps the
    earlier files on that disk (no link across filesystems), undoes and commits there."""
    folder = tmp_path / "cfg"
    seed(folder)
    tmpfs(folder / "export", "1m", 256)
    write_text(folder / "export" / "model.onnx", "old onnx")
    with pytest.raises(RuntimeError):
        with journal(folder):
            for rel, text in NEW.items():
                write_text(folder / rel, text)
            raise RuntimeError("the stage fails after its writes")
    assert state(folder) == OLD
    with journal(folder):
        for rel, text in NEW.items():
            write_text(folder / rel, text)
    assert state(folder) == NEW and not list(folder.rglob("*.undo"))
