"""The CUDA code paths against the CPU ones (``pytest -m gpu``; skipped without a GPU).

Training, exhaustive evaluation and table building each run on the GPU and are compared
with the same work on the CPU: a run trained on CUDA resumes exactly and its policy file
loads and acts on a CPU-only machine; a greedy policy acts the same on both devices; a table
built with the encoder and classifier on CUDA holds the CPU's features and probabilities up
to the GPU's rounding (TF32 convolutions).
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from uevavd.config import load_method
from uevavd.env.evaluate import evaluate_policy
from uevavd.policy.acting import GreedyPolicy, load_policy
from uevavd.policy.checkpoint import load_checkpoint
from uevavd.policy.trainer import train
from uevavd.testing.policy import small_run, toy_table

pytestmark = [pytest.mark.gpu, pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")]

@pytest.fixture(scope="module")
def table():
    return toy_table(n_train=3, n_hard=2, feature_dim=8)


# the generalisation training options too: the ensemble head, level replay's sampler, the features'
# dropout stream and the recognition probe keep their state on the run's device
@pytest.mark.parametrize("method", ["map", "memo_map", "ibe_map_ens", "ibe_map_plr", "ibe_map_aug", "ibe_map_aux"])
# cuDNN warns when a GRU's weights are not one flat buffer (then it compacts them every call);
# the target network's deep copy did that until 2026-11-24
@pytest.mark.filterwarnings("error:RNN module weights are not part of single contiguous chunk:UserWarning")
def test_cuda_run_resumes_exactly_and_its_policy_acts_on_cpu(table, tmp_path, method):
    spec = load_method(method)
    kw = dict(episodes=200, seed=3, progress=False, overrides=small_run(method), device="cuda")
    straight = train(spec, table, out=tmp_path / "a", **kw)
    train(spec, table, out=tmp_path / "b", max_epochs=1, **kw)
    resumed = train(spec, table, out=tmp_path / "b", **kw)
    wa, wb = load_checkpoint(straight / "checkpoint.pt")["net"], load_checkpoint(resumed / "checkpoint.pt")["net"]
    for k in wa:
        assert torch.equal(wa[k].cpu(), wb[k].cpu()), k
    assert all(v.device.type == "cpu" for v in wb.values())  # checkpoints load without CUDA
    on_cpu = evaluate_policy(table, "hard", load_policy(resumed, device="cpu"))
    on_gpu = evaluate_policy(table, "hard", load_policy(resumed, device="cuda"), device="cuda")
    assert np.isfinite(on_cpu.ret).all()
    same = (on_cpu.trajectories == on_gpu.trajectories).all(axis=1).mean()
    assert same > 0.99, f"only {same:.3f} of the episodes took the same views on both devices"
    np.testing.assert_allclose(on_cpu.ret.mean(), on_gpu.ret.mean(), atol=0.01)


def test_greedy_policy_acts_alike_on_cpu_and_cuda(table, tmp_path):
    run = train(load_method("ibe_map"), table, out=tmp_path / "r", episodes=200, seed=0, progress=False,
                overrides=small_run("ibe_map"), device="cpu")
    policy = load_policy(run, device="cpu")
    feats = torch.from_numpy(np.asarray(table.features))
    cpu = evaluate_policy(table, "train", GreedyPolicy(policy.net, features=feats))
    gpu = evaluate_policy(table, "train", GreedyPolicy(policy.net, device="cuda", features=feats.cuda()),
                          device="cuda")
    assert (cpu.trajectories == gpu.trajectories).all(axis=1).mean() > 0.99
    np.testing.assert_allclose(cpu.ret.mean(), gpu.ret.mean(), atol=0.01)


@pytest.mark.parametrize("reco", [False, True], ids=["features", "recognizer_in_state"])
def test_table_built_on_cuda_matches_cpu(tiny_world_gpu, tiny_classifier_gpu, tmp_path, reco):
    from uevavd.perception.prepare import prepare_table
    from uevavd.table import ObservationTable

    tables = {}
    for dev in ("cpu", "cuda"):
        method = tmp_path / f"{dev}.toml"
        method.write_text(METHOD_TOML.format(device=dev, reco=str(reco).lower()))
        path = prepare_table(tiny_world_gpu, method, classifier_path=tiny_classifier_gpu,
                             out_dir=tmp_path / dev, progress=False)
        tables[dev] = ObservationTable.load(path)
    a, b = tables["cpu"], tables["cuda"]
    fa, fb = np.asarray(a.features, np.float64), np.asarray(b.features, np.float64)
    assert fa.shape == fb.shape
    rel = np.linalg.norm(fa - fb) / np.linalg.norm(fa)
    assert rel < 1e-2, f"features differ by {rel:.2e} (relative)"
    assert np.abs(np.asarray(a.probs) - np.asarray(b.probs)).max() < 2e-2
    assert (np.asarray(a.probs).argmax(-1) == np.asarray(b.probs).argmax(-1)).mean() > 0.99
    np.testing.assert_array_equal(np.asarray(a.boxes), np.asarray(b.boxes))


METHOD_TOML = """
name = "tiny"
[perception]
segmenter = {{ name = "gt" }}
encoder = {{ name = "resnet18", weights = "random", seed = 0, device = "{device}" }}
classifier = {{ name = "resnet18", device = "{device}" }}
decompose = true
gray_seed = 0
recognizer_in_state = {reco}
"""


@pytest.fixture(scope="module")
def tiny_world_gpu(tmp_path_factory):
    from uevavd.testing.worlds import write_tiny_world

    return write_tiny_world(tmp_path_factory.mktemp("tiny-world"), contexts=(1, 31), train605=True)


@pytest.fixture(scope="module")
def tiny_classifier_gpu(tiny_world_gpu, tmp_path_factory):
    from uevavd.cli import main

    out = tmp_path_factory.mktemp("clf") / "tiny.safetensors"
    rc = main(["train-classifier", str(tiny_world_gpu), "--out", str(out), "--epochs", "2", "--max-views", "40",
               "--batch-size", "32", "--lr", "3e-3", "--device", "cuda"])
    assert rc == 0
    return out
