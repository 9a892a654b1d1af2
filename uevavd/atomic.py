"""Writing files so that nothing already written is lost: the one helper every layer uses.

A file is written to a temporary name in its own folder, then renamed over the target
(``os.replace`` is atomic on POSIX and Windows), so a reader sees the old file or the new
one, never half of one, and a killed or failed write leaves the old file in place and no
temporary behind. ``tempfile`` creates files 0600 and folders 0700, so the result gets the
permissions a plain ``open()`` / ``mkdir`` would give under the process's umask: a shared
cache, or a Ray worker running as another user, can read what uevavd wrote.
"""

from __future__ import annotations

import errno
import json
import os
import shutil
import tempfile
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from glob import escape as glob_escape
from pathlib import Path
from typing import IO, Any

from .hashing import DamagedFileError, seal, unseal


def _umask() -> int:
    mask = os.umask(0o022)  # reading the umask means setting it; restored at once
    os.umask(mask)
    return mask


#: The process's umask at import (uevavd never changes it).
_UMASK = _umask()
FILE_MODE = 0o666 & ~_UMASK
DIR_MODE = 0o777 & ~_UMASK


def atomic_write(path: str | os.PathLike[str], data: bytes | str | Callable[[IO[bytes]], None], *,
                 fsync: bool = False) -> Path:
    """Write ``data`` (bytes, text as UTF-8, or a function writing to a binary file object)
    to ``path`` atomically; ``fsync`` flushes it to the disk before the rename (for state a
    crash must not lose: checkpoints, shards). Returns ``path``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        os.fchmod(fd, FILE_MODE)
        with short_writes_named(path.parent), os.fdopen(fd, "wb") as fh:
            if callable(data):
                data(fh)
            else:
                fh.write(data.encode("utf-8") if isinstance(data, str) else data)
            if fsync:
                fh.flush()
                os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


#: Free bytes under which an errno-less write failure is taken for a full disk.
FULL_DISK_BYTES = 16 << 20


@contextmanager
def short_writes_named(folder: str | os.PathLike[str]) -> Iterator[None]:
    """numpy's writers report a failed write as a short one without an errno ("N requested and
    M written"), which read as a traceback. Inside this block such a failure in ``folder`` is
    the fault it is, which every command reports in one line: ``ENOSPC`` naming the folder
    where its disk is (nearly) full, ``EFBIG`` where the process has a file-size limit
    (``ulimit -f``); such an error with an errno but no file name gets the folder's. Any
    other error passes unchanged."""
    try:
        yield
    except OSError as exc:
        if exc.errno in _WRITE_FAULTS and exc.filename is None:  # Python's own write names no file
            raise OSError(exc.errno, exc.strerror, str(folder)) from None
        cause = _short_write_cause(exc, Path(folder))
        if cause is None:
            raise
        raise cause from None


#: The errors of a write that the disk or the process's limits refused.
_WRITE_FAULTS = (errno.ENOSPC, errno.EDQUOT, errno.EFBIG)


def _short_write_cause(exc: OSError, folder: Path) -> OSError | None:
    if exc.errno is not None:
        return None
    try:
        free = shutil.disk_usage(folder).free
    except OSError:
        free = FULL_DISK_BYTES
    if free < FULL_DISK_BYTES:
        return OSError(errno.ENOSPC, f"{folder}: the write stopped short ({exc}): no space left on the device")
    try:
        import resource
    except ImportError:  # not on Windows
        return None
    limit = resource.getrlimit(resource.RLIMIT_FSIZE)[0]
    if limit != resource.RLIM_INFINITY:
        return OSError(errno.EFBIG, f"{folder}: the write stopped short ({exc}): a file would pass the process's "
                                    f"file-size limit of {limit:,} bytes")
    return None


def remove_temporaries(folder: str | os.PathLike[str], name: str | None = None) -> list[Path]:
    """Remove what a killed :func:`atomic_write`, :func:`atomic_save` or :func:`atomic_dir`
    leaves in ``folder``: the temporaries of ``name`` (``.NAME.*.tmp*``, and ``.NAME.old-PID``
    folders moved aside), or of every name when None. Call it only while holding the lock of
    whatever writes there: a live writer's temporaries look the same. Returns what it removed."""
    folder = Path(folder)
    if not folder.is_dir():
        return []
    stem = "*" if name is None else glob_escape(name)
    gone = []
    for p in [*folder.glob(f".{stem}.*.tmp*"), *folder.glob(f".{stem}.old-*")]:
        if p.is_dir() and not p.is_symlink():
            shutil.rmtree(p, ignore_errors=True)
        else:
            p.unlink(missing_ok=True)
        gone.append(p)
    return gone


def is_temporary(path: str | os.PathLike[str]) -> bool:
    """Whether ``path`` is what a killed writer of this module leaves (``.NAME.*.tmp*``,
    ``.NAME.old-PID``): a folder holding only such files (and its own) holds nothing yet."""
    name = Path(path).name
    return name.startswith(".") and (".tmp" in name or ".old-" in name)


@contextmanager
def folder_lock(folder: str | os.PathLike[str], busy: Callable[[str], Exception], *,
                wait: Callable[[str], None] | None = None) -> Iterator[Path]:
    """Hold ``folder`` for one process, so a second process never interleaves its files with
    the first's: it is refused with ``busy(lock file)`` at once, or, given ``wait``, calls
    ``wait(lock file)`` (to say so) and waits its turn. The lock is a file beside the folder
    (``.NAME.lock``, so the folder holds its own files only); the OS releases it when its
    process ends, however it ends. Yields the lock file's path."""
    from filelock import FileLock, Timeout

    out = Path(folder).resolve()
    out.parent.mkdir(parents=True, exist_ok=True)
    lock = FileLock(str(out.parent / f".{out.name}.lock"))
    if Path(lock.lock_file).is_symlink():  # the lock never follows a link (the OS's ELOOP): say so, in one line
        raise ValueError(f"{lock.lock_file}: the lock file beside {out} is a symbolic link, which uevavd never "
                         f"makes; remove it (rm {lock.lock_file}) and run again")
    try:
        lock.acquire(timeout=0)
    except Timeout:
        if wait is None:
            raise busy(str(lock.lock_file)) from None
        wait(str(lock.lock_file))
        lock.acquire()
    try:
        yield Path(lock.lock_file)
    finally:
        lock.release()


def check_writable(path: str | os.PathLike[str]) -> Path:
    """Make ``path``'s folder and prove a file can be written in it (a temporary one, removed),
    so work whose result goes to ``path`` fails before it starts, not after (an unwritable
    ``--out`` failed after minutes of training). Raises the ``OSError`` naming the folder."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".probe")
    os.close(fd)
    os.unlink(tmp)
    return path


def json_text(obj: Any, *, sort_keys: bool = False) -> str:
    """The one JSON layout uevavd writes: indented by one space, a final newline, values JSON
    lacks (paths, numpy scalars) as their ``str``."""
    return json.dumps(obj, indent=1, sort_keys=sort_keys, default=str) + "\n"


def atomic_write_json(path: str | os.PathLike[str], obj: Any, *, sort_keys: bool = False,
                      fsync: bool = False) -> Path:
    """:func:`atomic_write` of :func:`json_text` of ``obj``."""
    return atomic_write(path, json_text(obj, sort_keys=sort_keys), fsync=fsync)


def write_sealed_json(path: str | os.PathLike[str], obj: dict[str, Any], *, sort_keys: bool = False,
                      fsync: bool = False) -> Path:
    """:func:`atomic_write_json` of ``obj`` :func:`~uevavd.hashing.seal`-ed (its digest under
    ``"sha256"``), for a file a reported number depends on; a reader checks it with
    :func:`read_sealed_json` (a cache, recomputed when edited) or :func:`load_sealed_json`
    (a record, refused when edited)."""
    return atomic_write_json(path, seal(obj), sort_keys=sort_keys, fsync=fsync)


def read_sealed_json(path: str | os.PathLike[str]) -> dict[str, Any] | None:
    """A :func:`write_sealed_json` cache's object, or None where it is missing, unreadable,
    unsealed or edited since it was written (a cache is then recomputed)."""
    try:
        return unseal(json.loads(Path(path).read_text(encoding="utf-8")), str(path), "")
    except (OSError, ValueError):
        return None


def load_sealed_json(path: str | os.PathLike[str], advice: str, *, legacy: bool = False) -> dict[str, Any]:
    """A :func:`write_sealed_json` record's object, checked: unreadable, edited or damaged is a
    :class:`~uevavd.hashing.DamagedFileError` naming the file and saying ``advice``;
    ``legacy`` takes an object without a seal as it is (files of earlier versions)."""
    path = Path(path)
    try:
        obj = json.loads(path.read_text(encoding="utf-8"))
    except ValueError as exc:  # not JSON, not UTF-8 (an OS fault is reported as one)
        raise DamagedFileError(f"{path}: unreadable ({exc}); {advice}") from None
    return unseal(obj, str(path), advice, legacy=legacy)


def atomic_save(path: str | os.PathLike[str], save: Callable[[str], None]) -> Path:
    """For libraries that write by file name (safetensors' ``save_file``, matplotlib's
    ``savefig``): ``save(tmp_name)``, then the rename of :func:`atomic_write`."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp" + path.suffix)
    os.close(fd)
    try:
        save(tmp)
        os.chmod(tmp, FILE_MODE)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


@contextmanager
def atomic_dir(path: str | os.PathLike[str]) -> Iterator[Path]:
    """Build a folder in a temporary sibling and put it in place of ``path`` when the block
    ends without an error (an existing ``path`` is moved aside first, then removed); on an
    error the temporary folder is removed and ``path`` is left as it was."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp"))
    try:
        os.chmod(tmp, DIR_MODE)
        yield tmp
        if path.exists():
            old = path.with_name(f".{path.name}.old-{os.getpid()}")
            os.replace(path, old)
            os.replace(tmp, path)
            shutil.rmtree(old, ignore_errors=True)
        else:
            os.replace(tmp, path)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
