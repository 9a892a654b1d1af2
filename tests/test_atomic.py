"""The one atomic-write helper: all or nothing, and the permissions a plain open() gives."""

from __future__ import annotations

import stat

import numpy as np
import pytest

from uevavd.atomic import DIR_MODE, FILE_MODE, atomic_dir, atomic_save, atomic_write


def _mode(path) -> int:
    return stat.S_IMODE(path.stat().st_mode)


def test_files_and_folders_get_the_umask_permissions_not_tempfiles_0600(tmp_path):
    """mkstemp makes 0600 and mkdtemp 0700: a shared cache or a Ray worker running as
    another user could not read what uevavd wrote."""
    plain = tmp_path / "plain.txt"
    plain.write_text("x")
    f = atomic_write(tmp_path / "a.json", "{}")
    assert _mode(f) == FILE_MODE == _mode(plain)
    s = atomic_save(tmp_path / "b.bin", lambda name: open(name, "wb").write(b"1"))
    assert _mode(s) == FILE_MODE
    with atomic_dir(tmp_path / "table") as d:
        (d / "x.npy").write_bytes(b"")
    assert _mode(tmp_path / "table") == DIR_MODE
    from uevavd.table import ObservationTable

    t = ObservationTable.from_arrays(np.zeros((1, 605, 2)), np.full((1, 605, 5), 0.2), np.zeros((1, 605, 4)),
                                     scenes=["001"], targets=[0], splits=["train"])
    saved = t.save(tmp_path / "t")
    assert _mode(saved) == DIR_MODE and {_mode(p) for p in saved.iterdir()} == {FILE_MODE}


def test_a_failed_write_keeps_the_old_file_and_leaves_no_temp(tmp_path):
    path = atomic_write(tmp_path / "state.bin", b"old")

    def boom(fh):
        fh.write(b"half")
        raise OSError(28, "No space left on device")

    with pytest.raises(OSError):
        atomic_write(path, boom)
    assert path.read_bytes() == b"old" and sorted(p.name for p in tmp_path.iterdir()) == ["state.bin"]
    with pytest.raises(RuntimeError), atomic_dir(tmp_path / "d") as d:
        (d / "f").write_text("x")
        raise RuntimeError("killed")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["state.bin"]


def test_json_files_have_one_layout_and_the_shipped_records_are_in_it(tmp_path):
    """Every JSON file uevavd writes goes through ``atomic_write_json``: one-space indent, a
    final newline, paths and numpy scalars as text. The shipped draws record and the zoo's
    manifest were written by it, so rewriting them changes no byte."""
    import json
    from pathlib import Path

    from uevavd.atomic import atomic_write_json, json_text
    from uevavd.data.synthetic.world import DRAWS_FILE
    from uevavd.zoo import Zoo

    f = atomic_write_json(tmp_path / "a.json", {"b": Path("x/y"), "a": np.float32(0.5)}, sort_keys=True)
    assert f.read_text() == '{\n "a": "0.5",\n "b": "x/y"\n}\n'
    draws = Path(DRAWS_FILE)
    assert json_text(json.loads(draws.read_text())) == draws.read_text()
    manifest = Zoo.load("quick").root / "manifest.json"
    assert json_text(json.loads(manifest.read_text()), sort_keys=True) == manifest.read_text()


def test_a_short_write_on_a_full_disk_is_enospc_naming_the_folder(tmp_path, monkeypatch):
    """numpy reports a full disk as a short write without an errno ("N requested and M
    written"), a traceback from `prepare`; with the disk (nearly) full it is ENOSPC now, which
    every command reports in one line. (No test machine can fill its disk: the free space is
    what the check reads, so it is what the test sets.)"""
    import errno
    import shutil
    from collections import namedtuple

    import pytest

    from uevavd.atomic import atomic_write

    def short(fh):
        fh.write(b"partial")
        raise OSError("1048576 requested and 4096 written")

    usage = namedtuple("usage", "total used free")
    monkeypatch.setattr(shutil, "disk_usage", lambda p: usage(10**9, 10**9 - 4096, 4096))
    with pytest.raises(OSError) as err:
        atomic_write(tmp_path / "a.npy", short)
    assert err.value.errno == errno.ENOSPC and str(tmp_path) in str(err.value)
    assert list(tmp_path.iterdir()) == []  # no temporary left
    monkeypatch.setattr(shutil, "disk_usage", lambda p: usage(10**12, 0, 10**12))
    with pytest.raises(OSError) as err:  # plenty of space: not taken for a full disk
        atomic_write(tmp_path / "a.npy", short)
    assert err.value.errno is None


def test_a_lock_file_that_is_a_symlink_is_one_line_and_its_target_untouched(tmp_path, capsys, monkeypatch):
    """An [Errno 40] traceback in train, prepare and export-minari."""
    from uevavd.atomic import folder_lock
    from uevavd.cli import main
    from uevavd.testing.policy import toy_table

    target = tmp_path / "target"
    target.write_text("keep")
    (tmp_path / ".run.lock").symlink_to(target)
    with pytest.raises(ValueError, match=r"\.run\.lock: the lock file beside .* is a symbolic link.*rm "):
        with folder_lock(tmp_path / "run", lambda f: RuntimeError(f)):
            pass
    monkeypatch.delenv("UEVAVD_DEBUG", raising=False)
    table = toy_table(n_train=2, n_hard=1, feature_dim=8).save(tmp_path / "table")
    assert main(["train", "--method", "map", "--table", str(table), "--episodes", "100", "--out",
                 str(tmp_path / "run"), "--no-progress"]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "is a symbolic link" in err and target.read_text() == "keep"
