"""Hashes: the one place that says how uevavd fingerprints files, bytes and JSON-able values.

``file_sha256`` is the full hex digest of a file (what manifests record and users compare with
``sha256sum``); ``sha256_hex`` hashes bytes or text; ``json_digest`` hashes a value as JSON
with sorted keys. Each cuts to ``n`` hex digits where the digest names a cache folder or a
file. Digests that stream many parts of one thing (a state dict's tensors, a table's arrays,
a dataset's files) feed ``hashlib`` in the module that knows those parts.
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


def json_digest(obj: Any, n: int | None = None, *, compact: bool = False) -> str:
    """sha256 of ``obj`` as JSON with sorted keys (``str`` for anything JSON lacks), the
    first ``n`` hex digits (all 64 when ``n`` is None). ``compact`` drops the spaces after
    separators: the form method-spec hashes and table keys were first written in, kept so
    that they name the same runs and tables."""
    separators = (",", ":") if compact else None
    return sha256_hex(json.dumps(obj, sort_keys=True, separators=separators, default=str), n)
