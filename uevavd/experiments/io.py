"""The ablation's own files: written atomically (a reader never sees half a file, and a full
disk leaves the previous version intact), and ``ablation.json`` sealed and checked where read."""

from __future__ import annotations

import csv
import json
import os
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

from ..atomic import atomic_write, load_sealed_json
from ..hashing import file_sha256, is_sealed

#: The ablation's record: its fingerprint (checked on a rerun), stages, status and the rows' roles.
ABLATION_FILE = "ablation.json"


def ablation_folder(path: str | os.PathLike[str]) -> Path:
    """``path`` as a Path when it is a folder, else the one-line refusal of ``report``."""
    if not (folder := Path(path)).is_dir():
        raise FileNotFoundError(f"{folder} is not a directory; expected an ablation directory holding results.csv")
    return folder


def read_ablation_meta(path: str | os.PathLike[str]) -> dict[str, Any]:
    """An ablation's ``ablation.json``, checked against the digest written in it (one of an
    earlier version, without one, is read as it is); damaged, edited or not a JSON object is
    an error naming the file."""
    return load_sealed_json(path, "restore it from a copy, or run the ablation again into a new --out",
                            legacy=not _runs_sealed(Path(path).parent))


#: The tables an ablation writes and seals in its ablation.json (``outputs``): the report reads them.
OUTPUTS = ("results.csv", "contexts.csv")


def output_digests(folder: str | os.PathLike[str]) -> dict[str, str]:
    """``{name: sha256}`` of the :data:`OUTPUTS` in ``folder`` (those that exist)."""
    return {name: file_sha256(Path(folder) / name) for name in OUTPUTS if (Path(folder) / name).is_file()}


def check_outputs(folder: str | os.PathLike[str], meta: dict[str, Any]) -> dict[str, Any]:
    """``meta``, after checking that each table its ``outputs`` records is the file the ablation wrote
    (a results.csv cut at a row boundary, or inside a field, kept its columns and lost rows); an
    ablation.json of an earlier version records none. A ValueError naming the file otherwise."""
    for name, digest in (meta.get("outputs") or {}).items():
        path = Path(folder) / name
        if not path.is_file() or file_sha256(path) != digest:
            raise ValueError(f"{path}: not the table the ablation wrote (missing, cut, edited or replaced: its sha256 "
                             f"is not the one {ABLATION_FILE} records); rerun the `uevavd ablate` that wrote it (it "
                             "resumes and writes the table again)")
    return meta


def _runs_sealed(ablation_dir: Path) -> bool:
    """Whether the ablation's first run on disk has a sealed settings.json: then this version wrote
    the ablation, and its ablation.json must carry its digest too (one without had it removed)."""
    first = next(iter(sorted(ablation_dir.glob("runs/*/*/*/*/settings.json"))), None)
    if first is None:
        return False
    try:
        return is_sealed(json.loads(first.read_text(encoding="utf-8")))
    except (OSError, ValueError):
        return False


def write_csv(path: str | os.PathLike[str], rows: Iterable[Mapping[str, Any]], columns: Sequence[str]) -> Path:
    """Write rows (dicts) as CSV with exactly ``columns``, atomically."""
    import io

    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=list(columns), extrasaction="raise", lineterminator="\n")
    writer.writeheader()
    for row in rows:
        writer.writerow({c: row.get(c, "") for c in columns})
    return atomic_write(path, buf.getvalue(), fsync=True)
