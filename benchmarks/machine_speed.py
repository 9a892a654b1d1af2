"""The machine-speed reference every benchmark prints beside its figures:
``../shared/tools/refwork.py`` (seconds of a fixed CPU workload) where the checkout has it.
Imported by the scripts in this folder (``python benchmarks/x.py`` puts it on the path)."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

TOOL = Path(__file__).resolve().parents[2] / "shared" / "tools" / "refwork.py"


def refwork() -> str:
    """The tool's line (``refwork 1.96``), or a line saying it is not there."""
    if not TOOL.is_file():
        return "refwork: not available"
    return subprocess.run([sys.executable, str(TOOL)], capture_output=True, text=True).stdout.strip() or "refwork: failed"


def refwork_seconds() -> float | None:
    """The tool's seconds, or None where it is not there."""
    found = re.search(r"(\d+(?:\.\d+)?)", refwork()) if TOOL.is_file() else None
    return float(found.group(1)) if found else None
