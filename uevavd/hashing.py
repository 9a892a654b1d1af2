"""Hashes: the one place that says how uevavd fingerprints files, bytes and JSON-able values.

``file_sha256`` is the full hex digest of a file (what manifests record and users compare with
``sha256sum``); ``sha256_hex`` hashes bytes or text; ``json_digest`` hashes a value as JSON
with sorted keys. Each cuts to ``n`` hex digits where the digest names a cache folder or a
file. Digests that stream many parts of one thing (a state dict's tensors, a table's arrays,
a dataset's files) feed ``hashlib`` in the module that knows those parts.

``seal`` / ``unseal`` are how a JSON object uevavd writes carries its own digest (under
:data:`SEAL`) and how a reader checks it: a run's settings, its evaluation rows, its finished
mark, a policy file's header, the caches of numbers. An edited or damaged object is a
:class:`DamagedFileError` naming where it was read.
"""

from __future__ import annotations

import hashlib
import json
import os
from typing import Any


def file_sha256(path: str | os.PathLike[str]) -> str:
    """The sha256 hex digest of a file's bytes (read in chunks)."""
    with open(path, "rb") as fh:
        return hashlib.file_digest(fh, "sha256").hexdigest()


def sha256_hex(data: bytes | str, n: int | None = None) -> str:
    """sha256 of ``data`` (a str as UTF-8), the first ``n`` hex digits (all 64 when None)."""
    digest = hashlib.sha256(data.encode() if isinstance(data, str) else data).hexdigest()
    return digest if n is None else digest[:n]


#: The key under which a sealed JSON object carries the sha256 of the rest of it.
SEAL = "sha256"


class DamagedFileError(ValueError):
    """A file (or a line of one) no longer matches the digest written with it: edited by hand,
    or damaged on the disk. Its message names the file and what to do."""


#: The key that says an object was written sealed, and the seal's format: an object claiming it
#: without its digest had the digest removed (earlier versions wrote neither key).
SEALED, SEAL_FORMAT = "sealed", "2"  # a string: safetensors headers hold strings only


def seal(obj: dict[str, Any]) -> dict[str, Any]:
    """``obj`` as it reads back from JSON, marked :data:`SEALED` and with its digest under :data:`SEAL`."""
    plain = json.loads(json.dumps(obj, default=str))
    plain.pop(SEAL, None)
    plain[SEALED] = SEAL_FORMAT
    return {**plain, SEAL: json_digest(plain)}


def is_sealed(obj: Any) -> bool:
    """Whether a JSON object read from a file carries a seal (this version's or an earlier one's)."""
    return isinstance(obj, dict) and (SEAL in obj or SEALED in obj)


def unseal(obj: Any, where: str, advice: str, *, legacy: bool = False) -> dict[str, Any]:
    """The sealed object ``obj`` read from ``where`` without its seal, after checking it. A
    digest that does not match, one removed from an object marked :data:`SEALED`, or an object
    that is not one, is a :class:`DamagedFileError` naming ``where`` and saying ``advice``.
    ``legacy``: an object with neither (written before the file kind was sealed) is taken as it
    is; a reader passes False where the file's sealed siblings show it is this version's."""
    if not isinstance(obj, dict):
        raise DamagedFileError(f"{where}: damaged (expected a JSON object, found {type(obj).__name__}); {advice}")
    if SEAL not in obj:
        if legacy and SEALED not in obj:
            return obj
        raise DamagedFileError(f"{where}: damaged or edited (no {SEAL} digest was found in it, and it was written "
                               f"sealed); {advice}")
    obj = dict(obj)
    recorded = obj.pop(SEAL)
    if recorded != json_digest(obj):
        raise DamagedFileError(f"{where}: edited or damaged since it was written (its content no longer matches "
                               f"the {SEAL} digest written with it); {advice}")
    obj.pop(SEALED, None)
    return obj


def arrays_sha256(*arrays: Any, n: int | None = None) -> str:
    """sha256 over numpy arrays, each by its dtype, shape and bytes (C order), the first ``n``
    hex digits (all 64 when None)."""
    import numpy as np

    h = hashlib.sha256()
    for a in arrays:
        a = np.ascontiguousarray(a)
        h.update(str((a.dtype.str, a.shape)).encode())
        h.update(memoryview(a).cast("B"))
    digest = h.hexdigest()
    return digest if n is None else digest[:n]


def json_digest(obj: Any, n: int | None = None, *, compact: bool = False) -> str:
    """sha256 of ``obj`` as JSON with sorted keys (``str`` for anything JSON lacks), the
    first ``n`` hex digits (all 64 when ``n`` is None). ``compact`` drops the spaces after
    separators: the form method-spec hashes and table keys were first written in, kept so
    that they name the same runs and tables."""
    separators = (",", ":") if compact else None
    return sha256_hex(json.dumps(obj, sort_keys=True, separators=separators, default=str), n)
