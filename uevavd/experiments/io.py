"""The ablation's own files: written atomically (a reader never sees half a file, and a full
disk leaves the previous version intact), and ``ablation.json`` sealed and checked where read."""

from __future__ import annotations

import csv
import os
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

from ..atomic import atomic_write, load_sealed_json

#: The ablation's record: its fingerprint (checked on a rerun), stages, status and the rows' roles.
ABLATION_FILE = "ablation.json"


def read_ablation_meta(path: str | os.PathLike[str]) -> dict[str, Any]:
    """An ablation's ``ablation.json``, checked against the digest written in it (one of an
    earlier version, without one, is read as it is); damaged, edited or not a JSON object is
    an error naming the file."""
    return load_sealed_json(path, "restore it from a copy, or run the ablation again into a new --out",
                            legacy=True)


def write_csv(path: str | os.PathLike[str], rows: Iterable[Mapping[str, Any]], columns: Sequence[str]) -> Path:
    """Write rows (dicts) as CSV with exactly ``columns``, atomically."""
    import io

    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=list(columns), extrasaction="raise", lineterminator="\n")
    writer.writeheader()
    for row in rows:
        writer.writerow({c: row.get(c, "") for c in columns})
    return atomic_write(path, buf.getvalue(), fsync=True)
