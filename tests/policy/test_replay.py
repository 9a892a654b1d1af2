"""Prioritised episode replay: the portable sampling (``TrainConfig.replay_sampling``), the default.

torch picks its vectorised kernels from the CPU (``torch.backends.cpu.get_cpu_capability()``:
AVX512 here, AVX2 on a CPU without AVX-512) and ``ATEN_CPU_CAPABILITY`` (read when torch loads)
selects a lower set, so a subprocess can sample with the kernels another CPU would run.
"""

from __future__ import annotations

import os
import subprocess
import sys

import pytest
import torch

from uevavd.policy.replay import EpisodeReplay

T_MAX = 5


def _add(buf: EpisodeReplay, k: int) -> None:
    """k one-decision episodes (their content does not matter to the sampling)."""
    z = torch.zeros(k, T_MAX, dtype=torch.int64)
    buf.add(torch.zeros(k, dtype=torch.int64), torch.zeros(k, T_MAX + 1, dtype=torch.int64), z, z,
            torch.zeros(k, T_MAX), torch.ones(k, dtype=torch.int64))


def _filled(n: int = 3000, capacity: int = 4000, seed: int = 0, sampling: str = "portable") -> EpisodeReplay:
    """A buffer of n one-decision episodes whose priorities are then spread over 4 decades."""
    gen = torch.Generator().manual_seed(seed)
    buf = EpisodeReplay(capacity, T_MAX, seed=seed, sampling=sampling)
    for start in range(0, n, 64):
        _add(buf, min(64, n - start))
    for _ in range(40):
        index = torch.randint(0, n, (64,), generator=gen)
        buf.update_priorities(index, 10.0 ** (4 * torch.rand(64, generator=gen) - 3))
    return buf


def test_importance_weights_are_the_usual_ones():
    """(w_i / min_j w_j)^-beta over the batch is (N P(i))^-beta / max_j (N P(j))^-beta."""
    buf = _filled()
    p = buf.priority[: buf.size].double() ** buf.alpha
    assert torch.allclose(buf.priority_alpha[: buf.size], p, rtol=1e-12, atol=0)
    batch = buf.sample(64, 0.4)
    want = (buf.size * p[batch.index] / p.sum()) ** -0.4
    assert torch.allclose(batch.weight.double(), want / want.max(), rtol=1e-6, atol=0)


def test_sampling_follows_priority_to_the_alpha():
    buf = EpisodeReplay(4, T_MAX, alpha=0.5, seed=1)
    _add(buf, 4)
    buf.update_priorities(torch.arange(4), torch.tensor([1.0, 4.0, 9.0, 16.0]) - buf.eps)
    counts = torch.bincount(torch.cat([buf.sample(1000, 0.4).index for _ in range(40)]), minlength=4)
    share = counts / counts.sum()
    assert torch.allclose(share, torch.tensor([1.0, 2.0, 3.0, 4.0]) / 10, atol=0.01)  # sqrt of the priorities


def test_a_restored_buffer_samples_as_the_original():
    buf = _filled()
    again = EpisodeReplay(buf.capacity, T_MAX)
    again.load_state_dict(buf.state_dict())
    a, b = buf.sample(64, 0.4), again.sample(64, 0.4)
    assert torch.equal(a.index, b.index) and torch.equal(a.weight, b.weight)


_SAMPLE = """
import hashlib, sys, torch
sys.path.insert(0, sys.argv[2])
import test_replay as t
from uevavd.policy.replay import EpisodeReplay
buf, h = t._filled(sampling=sys.argv[1]), hashlib.sha256()
for _ in range(20):
    batch = buf.sample(64, 0.4)
    h.update(batch.index.numpy().tobytes()); h.update(batch.weight.numpy().tobytes())
print(torch.backends.cpu.get_cpu_capability(), h.hexdigest())
"""


def _sampled_under(capability: str, sampling: str) -> str:
    env = {**os.environ, "ATEN_CPU_CAPABILITY": capability}
    out = subprocess.run([sys.executable, "-c", _SAMPLE, sampling, os.path.dirname(__file__)],
                         env=env, capture_output=True, text=True, check=True)
    return out.stdout.strip()


@pytest.mark.skipif(torch.backends.cpu.get_cpu_capability() != "AVX512",
                    reason="needs a CPU whose torch kernels are AVX-512, to compare them with AVX2's")
@pytest.mark.parametrize("sampling", [
    pytest.param("vectorised", marks=pytest.mark.xfail(strict=True, raises=AssertionError, reason=(
        "priority ** alpha and its sum run torch's vectorised kernels, whose last bits depend on the vector "
        "width: a CPU without AVX-512 samples other episodes (the sampling of runs before world version 5, "
        "kept to resume them)"))),
    "portable",  # the default since world version 5
])
def test_sampling_does_not_depend_on_the_cpus_vector_width(sampling):
    wide, narrow = _sampled_under("avx512", sampling), _sampled_under("avx2", sampling)
    assert wide.split()[0] == "AVX512" and narrow.split()[0] == "AVX2"
    assert wide.split()[1] == narrow.split()[1]
