"""Hashes: the one place that says how uevavd fingerprints files and JSON-able values.

``file_sha256`` is the full hex digest (what manifests record and users compare with
``sha256sum``); ``json_digest`` hashes a value as JSON with sorted keys, cut to ``n`` hex
digits where it names a cache folder or a file.
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


def json_digest(obj: Any, n: int | None = None) -> str:
    """sha256 of ``obj`` as JSON with sorted keys (``str`` for anything JSON lacks), the
    first ``n`` hex digits (all 64 when ``n`` is None)."""
    digest = hashlib.sha256(json.dumps(obj, sort_keys=True, default=str).encode()).hexdigest()
    return digest if n is None else digest[:n]
