"""The test suite's own setup (tests/conftest.py): where its temporary folders go."""

from __future__ import annotations

from pathlib import Path

import pytest


@pytest.fixture
def conftest(pytestconfig):
    """tests/conftest.py as pytest loaded it (each test folder has a module named conftest)."""
    return pytestconfig.pluginmanager.get_plugin(str(Path(__file__).with_name("conftest.py")))


def _mounts(tmp_path, line: str):
    path = tmp_path / "mounts"
    path.write_text(f"/dev/vda / ext4 rw,relatime 0 0\n{line}\n")
    return path


def test_temporary_folders_go_to_a_ram_disk_only_with_room(conftest, tmp_path):
    folder = tmp_path / "shm"
    folder.mkdir()
    tmpfs = _mounts(tmp_path, f"tmpfs {folder} tmpfs rw,nosuid,nodev 0 0")
    assert conftest._ram_temproot(tmpfs, str(folder), room=1) == str(folder)
    assert conftest._ram_temproot(tmpfs, str(folder), room=1 << 60) is None  # a small /dev/shm (docker: 64 MB)
    disk = _mounts(tmp_path, f"/dev/vdb {folder} ext4 rw 0 0")
    assert conftest._ram_temproot(disk, str(folder), room=1) is None  # not a RAM disk
    assert conftest._ram_temproot(tmp_path / "absent", str(folder), room=1) is None  # no /proc/mounts
    assert conftest._ram_temproot(tmpfs, str(tmp_path / "gone"), room=1) is None  # listed but not there


def test_the_ray_tests_run_one_after_the_other_after_the_first_ones_module(conftest, request):
    """They share one local Ray instance (tests/conftest.py): collected adjacent, in order,
    after every other test of the first one's module (whose fixtures it uses)."""
    ids = [item.nodeid for item in request.session.items]
    if not all(n in ids for n in conftest.RAY_TESTS):
        pytest.skip("the Ray tests are not all selected")
    at = ids.index(conftest.RAY_TESTS[0])
    assert ids[at:at + len(conftest.RAY_TESTS)] == list(conftest.RAY_TESTS)
    module = conftest.RAY_TESTS[0].split("::")[0] + "::"
    assert not [n for n in ids[at + 1:] if n.startswith(module)]
