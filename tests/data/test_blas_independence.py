"""The world's pixels do not depend on which BLAS kernel numpy loads.

numpy's OpenBLAS picks its kernel from the CPU: the AVX-512 one (``SkylakeX``) on the machine
that rendered the world's records, the AVX2 one (``Haswell``) on e.g. an AMD EPYC. Their
float32 matrix-vector products differ in the last bit, and the shading's Lambert term was one:
17 of the quick world's 30 context scenes hashed differently from the zoo's records on an AMD
machine (1-3 colour values per scene one level apart). ``OPENBLAS_CORETYPE`` (read when numpy loads) selects a kernel, so a subprocess can
render with either on a CPU that runs it.
"""

from __future__ import annotations

import os
import platform
import subprocess
import sys
from fractions import Fraction
from pathlib import Path

import numpy as np
import pytest

from uevavd.data.synthetic.shading import _fma_f32, rows_dot_f32


def _cpu_flags() -> set[str]:
    try:
        text = Path("/proc/cpuinfo").read_text()
    except OSError:
        return set()
    line = next((ln for ln in text.splitlines() if ln.startswith("flags")), "")
    return set(line.split(":", 1)[-1].split())


def _kernel_runs(kernel: str) -> bool:
    need = {"Haswell": {"avx2", "fma"}, "SkylakeX": {"avx512f", "avx512bw", "avx512dq", "avx512vl", "avx512cd"}}
    return platform.machine() in ("x86_64", "AMD64") and need[kernel] <= _cpu_flags()


def _in_subprocess(kernel: str, code: str, *args: str) -> str:
    env = {**os.environ, "OPENBLAS_CORETYPE": kernel}
    out = subprocess.run([sys.executable, "-c", code, *args], env=env, capture_output=True, text=True, check=True)
    return out.stdout.strip()


def _round_f32(x: Fraction) -> np.float32:
    """The float32 nearest to the exact ``x`` (ties to even)."""
    f = np.float32(float(x))  # within one float32 step of the answer
    cands = [f, np.nextafter(f, np.float32(np.inf)), np.nextafter(f, np.float32(-np.inf))]
    best = min(abs(Fraction(float(c)) - x) for c in cands)
    near = [c for c in cands if abs(Fraction(float(c)) - x) == best]
    return min(near, key=lambda c: int(np.asarray(c).view(np.uint32)) & 1)


def test_fused_multiply_add_rounds_once():
    # 1 + 2^-23 + (1 - 2^-46) 2^-24 lies just below the midpoint between 1 + 2^-23 and
    # 1 + 2^-22; its float64 sum lands on the midpoint, which rounded again would go to the
    # even neighbour, 1 + 2^-22
    x = np.array([1 + 2.0**-23], np.float32)
    y = np.float32(2.0**-24 * (1 - 2.0**-23))
    z = np.array([1 + 2.0**-23], np.float32)
    assert (x.astype(np.float64) * float(y) + z.astype(np.float64)).astype(np.float32)[0] == np.float32(1 + 2.0**-22)
    assert _fma_f32(x, y, z)[0] == np.float32(1 + 2.0**-23)
    rng = np.random.default_rng(0)
    xs, zs = (rng.standard_normal(3000) * 10.0 ** rng.integers(-3, 4, 3000)).astype(np.float32), \
        (rng.standard_normal(3000) * 10.0 ** rng.integers(-3, 4, 3000)).astype(np.float32)
    ys = rng.standard_normal(3).astype(np.float32)
    for y in ys:
        got = _fma_f32(xs, y, zs)
        want = [_round_f32(Fraction(float(a)) * Fraction(float(y)) + Fraction(float(c))) for a, c in zip(xs, zs, strict=True)]
        assert np.array_equal(got, np.array(want, np.float32))


@pytest.mark.skipif(not _kernel_runs("SkylakeX"), reason="needs a CPU with AVX-512 (OpenBLAS's SkylakeX kernel)")
def test_rows_dot_is_the_avx512_kernels_arithmetic(tmp_path):
    """``rows_dot_f32`` against numpy's ``@`` run by the kernel the world was rendered with,
    on every row count up to 70, around its switch at 16,384 rows and on a view's sizes."""
    sizes = [*range(2, 70), 4096, 16383, 16384, 16385, 16399, 65536]
    code = ("import sys, numpy as np\n"
            "rng = np.random.default_rng(1); v = rng.standard_normal(3).astype(np.float32); out = {'v': v}\n"
            "for n in map(int, sys.argv[2].split(',')):\n"
            "    a = (rng.standard_normal((n, 3)) * 10.0 ** rng.integers(-2, 3, (n, 3))).astype(np.float32)\n"
            "    out[f'a{n}'], out[f'r{n}'] = a, a @ v\n"
            "np.savez(sys.argv[1], **out)")
    _in_subprocess("SkylakeX", code, str(tmp_path / "ref.npz"), ",".join(map(str, sizes)))
    ref = np.load(tmp_path / "ref.npz")
    wrong = [n for n in sizes if not np.array_equal(rows_dot_f32(ref[f"a{n}"], ref["v"]), ref[f"r{n}"])]
    assert not wrong, f"row counts where rows_dot_f32 differs from the AVX-512 sgemv: {wrong}"


@pytest.mark.parametrize("kernel", ["Haswell", "SkylakeX"])
def test_a_scene_hashes_to_the_zoos_record_with_either_kernel(kernel, tmp_path):
    """Context 26 (hard split) is one of the scenes the AVX2 kernel used to shade otherwise."""
    if not _kernel_runs(kernel):
        pytest.skip(f"this CPU cannot run OpenBLAS's {kernel} kernel")
    from uevavd.zoo import Zoo, scene_digest

    # the scene is written with the kernel; its digest (of the file hashes scene.json records)
    # is read back here, so the subprocess imports the writer alone, not torch
    code = ("import sys; from pathlib import Path\n"
            "from uevavd.data.synthetic.writer import write_scene\n"
            "write_scene(Path(sys.argv[1]), '026', size=64, seed=0)")
    _in_subprocess(kernel, code, str(tmp_path))
    assert scene_digest(tmp_path / "026" / "scene.json") == Zoo.load("quick").manifest["world"]["scenes"]["026"]
