"""The command line refuses a simple mistake in about a second: before torch is imported."""

from __future__ import annotations

import subprocess
import sys

import pytest

#: A simple mistake per command; "{tmp}" is a scratch folder that exists.
MISTAKES = [
    ["ablate", "--seeds", "0", "--out", "{tmp}/o"], ["ablate", "--preset", "quik", "--out", "{tmp}/o"],
    ["ablate", "--methods", "mapp", "--out", "{tmp}/o"], ["ablate", "--sweep", "thr=1", "--out", "{tmp}/o"],
    ["demo", "--recognizers", "0", "--out", "{tmp}/o"],
    ["train", "--method", "map", "--table", "/nonexistent/table", "--out", "{tmp}/o"],
    ["train", "--method", "mapp", "--table", "{tmp}", "--out", "{tmp}/o"],
    ["train", "--method", "map", "--preset", "quik", "--table", "{tmp}", "--out", "{tmp}/o"],
    ["evaluate", "/nonexistent/run"],
    ["train-classifier", "/nonexistent/root"], ["train-classifier", "{tmp}", "--imagenet", "/nonexistent/r18.pth"],
    ["train-classifier", "{tmp}", "--threads", "0"],
    ["prepare", "/nonexistent/root", "--method", "map"],
    ["prepare", "{tmp}", "--method", "map", "--classifier", "/nonexistent/reco.safetensors"],
    ["export-minari", "{tmp}", "--id", "uevavd/x-v0", "--episodes", "0"],
    ["train-sam-small", "/nonexistent/root"],
    ["finetune-sam", "{tmp}", "--checkpoint", "/nonexistent/sam.pth", "--out", "{tmp}/o.safetensors"],
    ["synth", "--size", "-3", "--out", "{tmp}/w"],
    ["report", "/nonexistent/ablation"],
]


@pytest.mark.parametrize("argv", MISTAKES, ids=lambda a: " ".join(a[:3]))
def test_a_simple_mistake_is_refused_before_torch_is_imported(argv, tmp_path):
    """Every refusal of a simple mistake took 16-93 s under load: torch (about 3 s alone) was
    imported before the arguments, paths and files were checked. The checks run first now: one
    line, exit 2, torch not loaded (the test asserts that, not a timing)."""
    code = ("import sys; from uevavd.cli import main; rc = main(sys.argv[1:]); "
            "print(rc, 'torch' in sys.modules)")
    args = [a.replace("{tmp}", str(tmp_path)) for a in argv]
    out = subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True, timeout=120)
    assert out.stdout.split() == ["2", "False"], (out.stdout, out.stderr)
    assert len(out.stderr.strip().splitlines()) == 1 and "error:" in out.stderr, out.stderr
