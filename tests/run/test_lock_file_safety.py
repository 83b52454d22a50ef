"""Issue 31 item 1: the run lock never writes through a link. A symbolic link (to a file, to a missing file, to
/dev/null), a hard link or a FIFO in OUT/eligsir.lock is refused with one line, exit 4, and the target untouched."""

import os

import pytest

from eligsir_o3d.run.lock import LOCK_FILE, RunLock, RunLocked


@pytest.fixture
def victim(tmp_path):
    v = tmp_path / "victim.txt"
    v.write_text("precious\n")
    return v


@pytest.mark.parametrize("kind", ["symlink", "dangling", "hardlink", "fifo", "dir"])
def test_a_lock_file_that_is_a_link_or_special_is_refused_and_not_written(tmp_path, victim, kind):
    out = tmp_path / "out"
    out.mkdir()
    lock = out / LOCK_FILE
    if kind == "symlink":
        lock.symlink_to(victim)
    elif kind == "dangling":
        lock.symlink_to(tmp_path / "created-by-the-lock")
    elif kind == "hardlink":
        os.link(victim, lock)
    elif kind == "fifo":
        os.mkfifo(lock)
    else:
        lock.mkdir()
    before = victim.stat()
    with pytest.raises(RunLocked, match="not a plain file.*refusing to write the run lock"):
        with RunLock(out):
            pass
    assert victim.read_text() == "precious\n" and victim.stat().st_mtime_ns == before.st_mtime_ns
    assert not (tmp_path / "created-by-the-lock").exists()
    assert os.path.lexists(lock)  # the planted entry is left for its owner to look at, not removed


def test_the_cli_refuses_a_symlinked_lock_with_one_line(tmp_path, victim):
    from typer.testing import CliRunner

    from eligsir_o3d.cli.app import app

    out = tmp_path / "out"
    out.mkdir()
    (out / LOCK_FILE).symlink_to(victim)
    r = CliRunner().invoke(app, ["map", "synthetic", "--out", str(out), "--max-frames", "6", "--updates-per-frame",
                                 "1", "--no-pictures", "-q"])
    assert r.exit_code == 4 and "Traceback" not in r.output and "symbolic link" in r.output, r.output
    assert victim.read_text() == "precious\n"


def test_a_plain_lock_still_works_and_is_removed(tmp_path):
    with RunLock(tmp_path / "o"):
        assert (tmp_path / "o" / LOCK_FILE).is_file()
    assert not (tmp_path / "o" / LOCK_FILE).exists()
