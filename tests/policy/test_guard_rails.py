"""Guard rails of `uevavd train`: values checked by range before a run directory exists, a
table of another perception config refused, checkpoints tied to their seed and settings,
a full disk reported in one line."""

from __future__ import annotations

import json

import numpy as np
import pytest

from uevavd.cli import main
from uevavd.config import ConfigError, load_method
from uevavd.policy.checkpoint import CheckpointError
from uevavd.policy.rundir import read_settings, write_settings
from uevavd.policy.trainer import RunDirError, train

from .conftest import small
from .test_cli import _one_line_error as _one_line
from .test_cli import _sets


@pytest.mark.parametrize("key, value, needle", [
    ("train.checkpoint_every", 0, "train.checkpoint_every = 0: expected an integer >= 1"),
    ("train.target_update", 0, "train.target_update = 0: expected an integer >= 1"),
    ("train.batch_size", 0, "train.batch_size = 0: expected an integer >= 1"),
    ("train.updates_per_step", -1, "train.updates_per_step = -1"),
    ("train.learning_starts", 500, "no gradient update would ever run"),
    ("train.lr", 1e300, "train.lr = 1e+300: expected a learning rate in (0, 1]"),  # diverged mid-run
    # widths and sizes: 0 trained to nothing and "finished", -4 and huge ones were allocation tracebacks
    ("head.hidden", 0, "head.hidden = 0: expected a layer width, an integer in 1..8192"),
    ("head.hidden", 10**9, "head.hidden = 1000000000: expected a layer width"),
    ("state.state_dim", -4, "state.state_dim = -4: expected a layer width"),
    ("train.buffer_episodes", 10**9, "train.buffer_episodes = 1000000000: expected at most 10,000,000"),
    ("train.n_envs", 10**7, "train.n_envs = 10000000: expected at most 65,536"),
    ("env.t_max", 10**9, "EnvConfig.t_max=1000000000: expected an integer in 1..100"),
    # an infinite count of updates hung the run; infinite priorities crashed it mid-run and on resume
    ("train.updates_per_step", float("inf"), "train.updates_per_step = inf: expected a finite number"),
    ("train.updates_per_step", 5000, "train.updates_per_step = 5000: expected a number in (0, 1024]"),
    ("train.per_alpha", float("inf"), "train.per_alpha = inf: expected a finite number"),
    ("train.per_eps", float("inf"), "train.per_eps = inf: expected a finite number"),
    # finite but huge ones overflowed the float32 priorities after the run's files were written
    ("train.per_eps", 1e308, "train.per_eps = 1e+308: expected a small priority floor in (0, 1]"),
    ("train.per_alpha", 1e4, "train.per_alpha = 10000.0: expected a prioritisation exponent in [0, 10]"),
    ("train.per_alpha", 1e308, "train.per_alpha = 1e+308: expected a prioritisation exponent in [0, 10]"),
    ("train.stop_gate", "boxx", "train.stop_gate = 'boxx' has the wrong type: expected one of 'none', 'box', "
                                "'learned', 'pays', 'rule'"),
    # settings nothing reads under the options chosen were accepted and never read
    ("train.stop_threshold", 0.7, "train.stop_threshold = 0.7: expected its default 0.5: only the learned, pays and rule "
                                  "stop gates read it"),
    ("train.imitation_fraction", 0.5, "train.imitation_fraction = 0.5: expected its default 1.0"),
])
def test_out_of_range_training_values_are_refused_before_the_run_starts(table, tmp_path, capsys, monkeypatch,
                                                                        key, value, needle):
    monkeypatch.delenv("UEVAVD_DEBUG", raising=False)
    path = table.save(tmp_path / "table")
    out = tmp_path / "run"
    sets = _sets(**{key: value})
    if value == float("inf"):  # as a user types it: TOML's spelling
        sets[sets.index(f"{key}={json.dumps(value)}")] = f"{key}=inf"
    rc = main(["train", "--method", "map", "--table", str(path), "--episodes", "100", "--out", str(out),
               "--no-progress", "--device", "cpu", *sets])
    assert rc == 2
    _one_line(capsys, needle)
    assert not out.exists()  # nothing written: the directory is not locked to a bad config


def test_a_seed_past_32_bits_is_refused_naming_it(table, tmp_path, capsys, monkeypatch):
    """``--seed 10**20`` ended in an OverflowError naming no value, after the folder was made."""
    monkeypatch.delenv("UEVAVD_DEBUG", raising=False)
    path = table.save(tmp_path / "table")
    assert main(["train", "--method", "map", "--table", str(path), "--episodes", "100", "--seed", str(10**20),
                 "--out", str(tmp_path / "run"), "--no-progress", *_sets()]) == 2
    _one_line(capsys, "train.seed = 100000000000000000000: expected an integer in 0..4294967295")
    assert not (tmp_path / "run").exists()


def test_zero_episodes_are_refused(table, tmp_path, capsys, monkeypatch):
    monkeypatch.delenv("UEVAVD_DEBUG", raising=False)
    path = table.save(tmp_path / "table")
    assert main(["train", "--method", "map", "--table", str(path), "--episodes", "0", "--out",
                 str(tmp_path / "run"), "--no-progress", *_sets()]) == 2
    _one_line(capsys, "train.episodes = 0")


def test_a_table_of_another_perception_config_is_refused(table, tmp_path):
    """IBE-MAP on a table whose meta.json says raw (undecomposed) features, or MAP's
    ResNet50 on a ResNet18 table: refused, naming what differs."""
    from uevavd.table import ObservationTable

    raw = {"segmenter": {"name": "none"}, "decompose": False, "encoder": {"name": "resnet18", "weights": "imagenet"},
           "classifier": {"name": "resnet18"}}
    t = ObservationTable.from_arrays(table.features, table.probs, table.boxes, scenes=table.scenes,
                                     targets=table.targets, splits=table.splits, contexts=table.contexts,
                                     config={"perception": raw})
    path = t.save(tmp_path / "raw-table")
    ibe = load_method("ibe_map", overrides={**small("ibe_map"), "train.episodes": 100})
    with pytest.raises(RunDirError, match=r"perception.segmenter.name: table 'none', method 'gt'.*decompose"):
        train(ibe, path, out=tmp_path / "ibe", device="cpu", progress=False)
    mp = load_method("map", overrides={**small("map"), "train.episodes": 100})
    with pytest.raises(RunDirError, match=r"perception.encoder.name: table 'resnet18', method 'resnet50'"):
        train(mp, path, out=tmp_path / "map", device="cpu", progress=False)
    assert not (tmp_path / "ibe").exists() and not (tmp_path / "map").exists()
    same = load_method("map", overrides={**small("map"), "train.episodes": 100,
                                         "perception.encoder.name": "resnet18", "perception.encoder.weights": "imagenet"})
    train(same, path, out=tmp_path / "ok", device="cpu", progress=False)  # the matching method trains


def test_recognizer_in_state_set_false_trains_on_the_plain_table_prepare_gives(table, tmp_path):
    """`--set perception.recognizer_in_state=false` on ibe_map_reco was a dead end: train refused
    the plain table (which records the key only when true), and prepare handed back that table."""
    from uevavd.table import ObservationTable

    plain = load_method("ibe_map").perception.as_dict()
    t = ObservationTable.from_arrays(table.features, table.probs, table.boxes, scenes=table.scenes,
                                     targets=table.targets, splits=table.splits, contexts=table.contexts,
                                     config={"perception": plain})
    off = load_method("ibe_map_reco", overrides={**small("ibe_map"), "train.episodes": 100,
                                                 "perception.recognizer_in_state": False})
    train(off, t, out=tmp_path / "off", device="cpu", progress=False)
    on = load_method("ibe_map_reco", overrides={**small("ibe_map"), "train.episodes": 100})
    with pytest.raises(RunDirError, match=r"perception.recognizer_in_state: table False, method True"):
        train(on, t, out=tmp_path / "on", device="cpu", progress=False)


def test_a_checkpoint_of_another_seed_is_refused(table, tmp_path):
    """A seed-1 checkpoint copied into an unfinished seed-0 run of the same method: refused
    (it used to resume as seed 0)."""
    import shutil

    spec = load_method("map", overrides={**small("map"), "train.episodes": 300})
    for seed in (0, 1):
        train(spec, table, out=tmp_path / f"s{seed}", seed=seed, device="cpu", progress=False, max_epochs=1)
    shutil.copy(tmp_path / "s1" / "checkpoint.pt", tmp_path / "s0" / "checkpoint.pt")
    with pytest.raises(CheckpointError, match="seed: checkpoint has 1, expected 0"):
        train(spec, table, out=tmp_path / "s0", seed=0, device="cpu", progress=False)


def test_a_full_disk_while_checkpointing_is_one_line(table, tmp_path, capsys, monkeypatch):
    """torch says "unexpected pos" when the disk fills during a save: the user reads one line
    saying the disk is full, exit 2, and no temp file is left behind."""
    import torch

    monkeypatch.delenv("UEVAVD_DEBUG", raising=False)

    def full(*a, **k):
        raise RuntimeError("[enforce fail at inline_container.cc:783] . PytorchStreamWriter failed writing file "
                           "data/0: file write failed; unexpected pos 64 vs 4096")

    monkeypatch.setattr(torch, "save", full)
    path = table.save(tmp_path / "table")
    out = tmp_path / "run"
    writers = _tensorboard_writer_threads()
    rc = main(["train", "--method", "map", "--table", str(path), "--episodes", "100", "--out", str(out),
               "--no-progress", "--device", "cpu", *_sets()])
    assert rc == 2
    _one_line(capsys, "[Errno 28]", "disk full", "checkpoint.pt")
    assert not list(out.glob(".checkpoint.pt.*"))
    # the failed run closed its TensorBoard writer: no thread is left writing into the run folder
    assert _tensorboard_writer_threads() <= writers


def _tensorboard_writer_threads() -> set:
    import threading

    from tensorboard.summary.writer.event_file_writer import _AsyncWriterThread

    return {t for t in threading.enumerate() if isinstance(t, _AsyncWriterThread) and t.is_alive()}


def test_range_checks_live_in_the_config(table):
    from uevavd.policy.config import TrainConfig

    with pytest.raises(ConfigError, match="train.eps_fraction = 0"):
        TrainConfig(eps_fraction=0.0)
    TrainConfig.from_dict({"episodes": 10, "learning_starts": 5})


class _PlainState(__import__("torch").nn.Module):
    """A third-party estimator that follows the documented protocol (forward, step,
    initial_hidden) without the optional ``step_encoded`` fast path."""

    def __init__(self, inner):
        super().__init__()
        self.inner = inner
        self.feature_dim, self.state_dim, self.recurrent = inner.feature_dim, inner.state_dim, inner.recurrent

    def forward(self, features, boxes):
        return self.inner(features, boxes)

    def initial_hidden(self, n, device="cpu"):
        return self.inner.initial_hidden(n, device)

    def step(self, features, boxes, hidden):
        return self.inner.step(features, boxes, hidden)


def build_plain_state(*, feature_dim: int, input_dim: int = 544, box_dim: int = 32, state_dim: int = 512):
    from uevavd.state.single_view import build_single_view

    return _PlainState(build_single_view(feature_dim=feature_dim, input_dim=input_dim, box_dim=box_dim,
                                         state_dim=state_dim))


def test_an_estimator_without_the_optional_fast_path_trains_and_is_evaluated(table, tmp_path):
    """It passes the contract check and used to crash in the first per-epoch evaluation
    (the evaluator built its observations without features)."""
    import types

    from uevavd.plugins import hookimpl
    from uevavd.plugins.manager import manager
    from uevavd.testing import check_state_estimator

    @hookimpl
    def register_state_estimators(registry):
        registry.add("plain_single_view", f"{__name__}:build_plain_state")

    manager.register_plugin(types.SimpleNamespace(register_state_estimators=register_state_estimators),
                            name="plain-state-test")
    try:
        check_state_estimator(build_plain_state(feature_dim=8, input_dim=24, box_dim=8, state_dim=16))
        spec = load_method("map", overrides={**small("map"), "train.episodes": 200, "state.name": "plain_single_view"})
        run = train(spec, table, out=tmp_path / "run", device="cpu", progress=False)
        evals = [json.loads(line) for line in (run / "evals.jsonl").read_text().splitlines()]
        assert evals and all(np.isfinite(e["mean_return"]) for e in evals)
    finally:
        manager.unregister_plugin("plain-state-test")


def test_a_cuda_device_that_is_not_there_is_one_line(table, tmp_path, capsys, monkeypatch):
    import torch

    monkeypatch.delenv("UEVAVD_DEBUG", raising=False)
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    path = table.save(tmp_path / "table")
    assert main(["train", "--method", "map", "--table", str(path), "--episodes", "100", "--out",
                 str(tmp_path / "run"), "--device", "cuda", "--no-progress", *_sets()]) == 2
    _one_line(capsys, "device 'cuda' requested but no CUDA device is available")
    assert not (tmp_path / "run").exists()


def test_a_corrupt_settings_json_is_named(table, tmp_path, capsys, monkeypatch):
    monkeypatch.delenv("UEVAVD_DEBUG", raising=False)
    path = table.save(tmp_path / "table")
    run = tmp_path / "run"
    assert main(["train", "--method", "map", "--table", str(path), "--episodes", "100", "--out", str(run),
                 "--no-progress", "--device", "cpu", *_sets()]) == 0
    capsys.readouterr()
    for damaged, line in (("{not json", "unreadable"), ("[1, 2]", "damaged (expected a JSON object, found list)")):
        (run / "settings.json").write_text(damaged)
        assert main(["evaluate", str(run), "--split", "hard"]) == 2
        _one_line(capsys, f"{run / 'settings.json'}: {line}")
        # a rerun of train on it (a resume) names the file too: a JSON list was a TypeError
        assert main(["train", "--method", "map", "--table", str(path), "--episodes", "100", "--out", str(run),
                     "--no-progress", "--device", "cpu", *_sets()]) == 2
        _one_line(capsys, f"{run / 'settings.json'}: {line}")


def test_a_killed_saves_temp_file_is_removed_on_resume(table, tmp_path):
    spec = load_method("map", overrides={**small("map"), "train.episodes": 300})
    run = train(spec, table, out=tmp_path / "run", device="cpu", progress=False, max_epochs=1)
    stale = run / ".checkpoint.pt.abc123.tmp"
    stale.write_bytes(b"\0" * 4096)  # what a kill during torch.save leaves
    train(spec, table, out=run, device="cpu", progress=False)
    assert not stale.exists() and (run / "done.json").is_file()


def test_a_run_another_process_is_training_is_refused_in_one_line(table, tmp_path, capsys, monkeypatch):
    """`uevavd train` into a run directory another process holds (the same command started
    twice, two ablations with one --out): one line, exit 2, nothing of the run written; it
    used to interleave both processes' checkpoints and evaluations. Once the other process
    ends (however it ends: the OS drops its lock), the run trains."""
    import subprocess
    import sys

    monkeypatch.delenv("UEVAVD_DEBUG", raising=False)
    path = table.save(tmp_path / "table")
    run = tmp_path / "run"
    holder = subprocess.Popen(  # the lock a trainer holds: .NAME.lock beside the run directory
        [sys.executable, "-c", "import sys; from filelock import FileLock\n"
         "with FileLock(sys.argv[1]):\n    print('held', flush=True); sys.stdin.read()",
         str(tmp_path / ".run.lock")], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    args = ["train", "--method", "map", "--table", str(path), "--episodes", "100", "--out", str(run),
            "--no-progress", "--device", "cpu", *_sets()]
    try:
        assert holder.stdout.readline().strip() == "held"
        assert main(args) == 2
        _one_line(capsys, f"{run} is being trained by another process")
        assert not run.exists()
    finally:
        holder.kill()
        holder.wait()
    assert main(args) == 0 and (run / "done.json").is_file()


def test_the_replays_sampling_is_a_recorded_setting_checked_on_resume(table, tmp_path):
    """train.replay_sampling changes the trained weights: it is recorded in settings.json
    ("portable" by default since world version 5), a resume with the other value is refused
    naming it, and a run recorded before the setting existed resumes as it trained
    ("vectorised")."""
    import torch

    spec = load_method("map", overrides={**small("map"), "train.episodes": 300})
    out = train(spec, table, out=tmp_path / "run", device="cpu", progress=False, max_epochs=1)
    settings = json.loads((out / "settings.json").read_text())
    assert settings["train"]["replay_sampling"] == "portable"
    with pytest.raises(RunDirError, match="train.replay_sampling: run has 'portable', now 'vectorised'"):
        train(spec, table, out=out, device="cpu", progress=False,
              overrides={"train.replay_sampling": "vectorised"})
    # the same run, as a run of the earlier version recorded it: no replay_sampling (nor
    # env.train_per_block, which came after it) anywhere
    old = load_method("map", overrides={**small("map"), "train.episodes": 300, "train.replay_sampling": "vectorised"})
    legacy = train(old, table, out=tmp_path / "legacy", device="cpu", progress=False, max_epochs=1)
    settings = json.loads((legacy / "settings.json").read_text())
    del settings["train"]["replay_sampling"], settings["env"]["train_per_block"], settings["sha256"]  # unsealed then
    del settings["sealed"]
    (legacy / "settings.json").write_text(json.dumps(settings))
    rows = [json.loads(line) for line in (legacy / "evals.jsonl").read_text().splitlines()]  # unsealed too
    (legacy / "evals.jsonl").write_text("".join(json.dumps({k: v for k, v in r.items() if k not in (
        "sha256", "sealed", "run")}) + "\n" for r in rows))
    ck = torch.load(legacy / "checkpoint.pt", weights_only=True)
    del ck["meta"]["train"]["replay_sampling"], ck["meta"]["env"]["train_per_block"]
    torch.save(ck, legacy / "checkpoint.pt")
    with pytest.raises(RunDirError, match="train.replay_sampling: run has 'vectorised', now 'portable'"):
        train(spec, table, out=legacy, device="cpu", progress=False)
    train(old, table, out=legacy, device="cpu", progress=False)  # resumes and finishes
    assert (legacy / "policy.safetensors").is_file()


def test_the_two_replay_samplings_train_different_weights(table, tmp_path):
    """The setting matters (else recording it would be noise): the same seed trains other
    weights under the two samplings."""
    from safetensors.torch import load_file

    def weights(sampling: str) -> dict:
        spec = load_method("map", overrides={**small("map"), "train.episodes": 300, "train.replay_sampling": sampling})
        out = train(spec, table, out=tmp_path / sampling, device="cpu", progress=False)
        return load_file(out / "policy.safetensors")

    a, b = weights("portable"), weights("vectorised")
    assert any(not (a[k] == b[k]).all() for k in a)


@pytest.fixture(scope="module")
def whole_run(table, tmp_path_factory):
    """``(spec, folder)``: a finished 200-episode MAP run, the uninterrupted reference of the
    kill cases below (they only read it)."""
    spec = load_method("map", overrides={**small("map"), "train.episodes": 200})
    return spec, train(spec, table, out=tmp_path_factory.mktemp("whole") / "run", device="cpu", progress=False)


@pytest.mark.parametrize("left", [
    ("method.toml",), ("settings.json",),
    (".settings.json.k1ll3d.tmp",),  # killed while writing its first file
    ("settings.json", "method.toml", "evals.jsonl", ".checkpoint.pt.k1ll3d.tmp"),  # inside its first checkpoint
])
def test_a_run_killed_before_its_first_checkpoint_resumes(table, tmp_path, left, whole_run):
    """A kill after method.toml (the order of earlier versions) or after settings.json (now
    written first), before the other, or while either was written (a temporary file), or in
    the first checkpoint's save: the rerun trains the run instead of calling the folder
    someone else's; it ends with the weights of an uninterrupted run."""
    from safetensors.torch import load_file

    spec, whole = whole_run
    killed = tmp_path / "killed"
    killed.mkdir()
    for name in left:
        own = name.split(".")[1] + "." + name.split(".")[2] if name.startswith(".") else name
        data = (whole / own).read_bytes()
        (killed / name).write_bytes(data[: len(data) // 2] if name.startswith(".") else data)
    train(spec, table, out=killed, device="cpu", progress=False)
    a, b = load_file(whole / "policy.safetensors"), load_file(killed / "policy.safetensors")
    assert all((a[k] == b[k]).all() for k in a)
    assert not [p for p in killed.iterdir() if p.name.startswith(".")]


def test_a_run_evaluates_its_held_out_training_contexts_as_the_validation_split(table, tmp_path):
    """train.eval_splits = ["train", "validation"] with env.train_per_block: the per-epoch and
    final evaluations cover the trained contexts and the held-out ones apart."""
    spec = load_method("map", overrides={**small("map"), "train.episodes": 200, "env.train_per_block": 2,
                                         "train.eval_splits": ["train", "validation"], "train.eval_contexts": 0})
    out = train(spec, table, out=tmp_path / "run", device="cpu", progress=False)
    done = json.loads((out / "done.json").read_text())
    final = {r["split"]: r for r in done["final_eval"]}
    assert set(final) == {"train", "validation"}
    assert final["train"]["eval_episodes"] == 2 * 605 and final["validation"]["eval_episodes"] == 605


def test_an_infinite_or_nan_learning_rate_is_refused():
    from uevavd.policy.config import TrainConfig

    for lr in (float("inf"), float("nan"), 0.0, 2.0):
        with pytest.raises(ConfigError, match=r"train.lr = .*: expected a learning rate in \(0, 1\]"):
            TrainConfig(lr=lr)


@pytest.mark.parametrize("value", ["0", "-1"])
def test_max_epochs_below_one_is_refused_before_anything_is_written(table, tmp_path, capsys, monkeypatch, value):
    """--max-epochs 0 / -1 used to train one epoch."""
    monkeypatch.delenv("UEVAVD_DEBUG", raising=False)
    path = table.save(tmp_path / "table")
    out = tmp_path / "run"
    rc = main(["train", "--method", "map", "--table", str(path), "--episodes", "200", "--out", str(out),
               "--no-progress", "--device", "cpu", "--max-epochs", value, *_sets()])
    assert rc == 2
    _one_line(capsys, f"max_epochs = {value}: expected an integer >= 1")
    assert not out.exists()


def _flip(path, at: float | None = None, offset: int | None = None) -> None:
    """Flip one bit of a file in place, at a share ``at`` of it or a byte ``offset``."""
    data = bytearray(path.read_bytes())
    i = offset if offset is not None else int(len(data) * at)
    data[i] ^= 0x10
    path.write_bytes(bytes(data))


def _record_data_offset(path, at: float) -> int:
    """The middle byte of the data of the zip record that holds the byte at share ``at`` of the file."""
    import struct
    import zipfile

    data = path.read_bytes()
    with zipfile.ZipFile(path) as z:
        infos = sorted((i for i in z.infolist() if i.compress_size > 0), key=lambda i: i.header_offset)
    record = [i for i in infos if i.header_offset <= int(len(data) * at)][-1]
    name_len, extra_len = struct.unpack("<HH", data[record.header_offset + 26:record.header_offset + 30])
    return record.header_offset + 30 + name_len + extra_len + record.compress_size // 2


def _safetensors_data_start(path) -> int:
    import struct

    return 8 + struct.unpack("<Q", path.read_bytes()[:8])[0]


def test_a_flipped_bit_in_a_checkpoint_or_a_policy_file_is_refused_naming_it(table, tmp_path):
    """torch.load ignores the zip's CRCs: a checkpoint with one flipped bit resumed (to other
    weights) and evaluated without complaint; a flipped bit in policy.safetensors was loaded."""
    import shutil

    from uevavd.policy.checkpoint import load_checkpoint, read_policy_file

    spec = load_method("map", overrides={**small("map"), "train.episodes": 200})
    run = tmp_path / "run"
    train(spec, table, out=run, device="cpu", progress=False)
    for at in (0.3, 0.6):  # inside the data of the records there (a flip in a header's padding changes nothing)
        ck = tmp_path / f"ck{at}.pt"
        shutil.copy(run / "checkpoint.pt", ck)
        _flip(ck, offset=_record_data_offset(ck, at))
        with pytest.raises(CheckpointError, match=rf"{ck.name}: (damaged|unreadable) checkpoint"):
            load_checkpoint(ck)
    load_checkpoint(run / "checkpoint.pt")  # the intact one loads
    policy = tmp_path / "policy.safetensors"
    shutil.copy(run / "policy.safetensors", policy)
    _flip(policy, offset=_safetensors_data_start(policy) + 101)
    with pytest.raises(CheckpointError, match="policy.safetensors: damaged"):
        read_policy_file(policy)
    read_policy_file(run / "policy.safetensors")


def test_a_flipped_bit_in_a_cached_recognizer_is_refused(tmp_path):
    """One exponent bit in a cached recognizer's weights moved train accuracy 0.78 -> 0.92 and
    was reused; its weights are checked against the weights_hash written with them now."""
    import shutil
    from pathlib import Path

    from uevavd.perception.classifier import read_classifier_file
    from uevavd.perception.weights import WeightsError

    shipped = Path(__file__).resolve().parents[2] / "uevavd/model_zoo/pretrained/quick/recognizer.safetensors"
    copy = tmp_path / "recognizer.safetensors"
    shutil.copy(shipped, copy)
    read_classifier_file(copy)
    _flip(copy, offset=_safetensors_data_start(copy) + 4099)
    with pytest.raises(WeightsError, match="recognizer.safetensors: damaged"):
        read_classifier_file(copy)


def test_an_unfinished_run_resumes_only_on_the_kind_of_device_it_started_on(table, tmp_path, capsys, monkeypatch):
    """The device changes a run's numbers: resumed on another kind, a run paused on a GPU
    went on on the CPU and ended as no uninterrupted run would. (No GPU here: the run's
    recorded device is set as a run started on one records it.)"""
    monkeypatch.delenv("UEVAVD_DEBUG", raising=False)
    path = table.save(tmp_path / "table")
    run = tmp_path / "run"
    args = ["train", "--method", "map", "--table", str(path), "--episodes", "300", "--out", str(run),
            "--no-progress", "--device", "cpu", *_sets()]
    assert main([*args, "--max-epochs", "1"]) == 0
    capsys.readouterr()
    settings = read_settings(run)
    write_settings(run, {**settings, "device": "cuda:0"})  # as a run started on a GPU records it
    assert main(args) == 2
    _one_line(capsys, f"{run} was trained on cuda:0 so far; resuming it on cpu", "resume with --device cuda:0")
    write_settings(run, settings)
    assert main(args) == 0 and (run / "done.json").is_file()  # on its own device it resumes
    write_settings(run, {**settings, "device": "cuda:0"})
    assert main(args) == 0  # a finished run is finished on any device


def test_a_holdout_block_that_empties_the_training_split_names_the_setting(table, tmp_path, capsys, monkeypatch):
    """It blamed the table: "no scenes in split 'train' (splits present: [..., 'train'])"."""
    monkeypatch.delenv("UEVAVD_DEBUG", raising=False)
    path = table.save(tmp_path / "table")
    assert main(["train", "--method", "map", "--table", str(path), "--episodes", "100", "--out",
                 str(tmp_path / "run"), "--no-progress", *_sets(**{"env.holdout_block": 1})]) == 2
    _one_line(capsys, "env.holdout_block = 1 holds out every training context of table")


def test_a_checkpoint_that_is_not_a_zip_is_named_as_such(table, tmp_path):
    from uevavd.policy.checkpoint import load_checkpoint

    spec = load_method("map", overrides={**small("map"), "train.episodes": 200})
    train(spec, table, out=tmp_path / "run", device="cpu", progress=False)
    cut = tmp_path / "cut.pt"
    cut.write_bytes((tmp_path / "run" / "checkpoint.pt").read_bytes()[:1000])  # a write cut short
    with pytest.raises(CheckpointError, match=r"not a readable zip archive: .*a write cut short"):
        load_checkpoint(cut)
