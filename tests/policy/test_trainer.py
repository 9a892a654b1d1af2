import json

import pytest
import torch

from uevavd.config import load_method
from uevavd.policy.acting import load_policy
from uevavd.policy.checkpoint import CheckpointError, load_checkpoint, read_policy_file
from uevavd.policy.trainer import RunDirError, train

from .conftest import small


def _weights(run):
    return load_checkpoint(run / "checkpoint.pt")["net"]


def test_interrupted_and_resumed_run_equals_straight_run(table, tmp_path):
    spec = load_method("memo_map")
    kw = dict(episodes=200, seed=3, progress=False, overrides=small("memo_map"), device="cpu")
    straight = train(spec, table, out=tmp_path / "a", **kw)
    first = train(spec, table, out=tmp_path / "b", max_epochs=1, **kw)
    assert not (first / "done.json").exists()
    assert not (first / "policy.safetensors").exists()  # only a finished run writes the shareable policy
    resumed = train(spec, table, out=tmp_path / "b", **kw)
    assert (resumed / "done.json").exists()
    wa, wb = _weights(straight), _weights(resumed)
    assert wa.keys() == wb.keys()
    for k in wa:
        assert torch.equal(wa[k], wb[k]), k
    shared = read_policy_file(resumed / "policy.safetensors")
    assert shared[1]["method"] == "memo_map" and shared[1]["seed"] == 3
    assert all(torch.equal(shared[2][k], wb[k]) for k in wb) and shared[2].keys() == wb.keys()
    rows = [json.loads(line) for line in (resumed / "evals.jsonl").read_text().splitlines()]
    assert [(r["epoch"], r["split"]) for r in rows] == [(1, "train"), (1, "hard"), (2, "train"), (2, "hard")]
    # a finished run returns at once; another configuration is refused, naming the difference
    assert train(spec, table, out=tmp_path / "b", **kw) == resumed
    with pytest.raises(RunDirError, match="seed"):
        train(spec, table, out=tmp_path / "b", **{**kw, "seed": 4})
    from uevavd.env.evaluate import evaluate_policy
    from uevavd.policy.acting import GreedyPolicy

    policy = load_policy(resumed)
    assert policy.needs_features  # an in-memory table has no folder to read features from
    plain = evaluate_policy(table, "hard", policy)
    assert len(plain) == 2 * 605
    # projecting every (scene, view) once gives the same actions as encoding per step
    fast = GreedyPolicy(policy.net, features=torch.from_numpy(table.features))
    assert not fast.needs_features
    assert (evaluate_policy(table, "hard", fast).trajectories == plain.trajectories).all()


def test_checkpoint_of_another_method_is_refused(table, tmp_path):
    run = train(load_method("map"), table, out=tmp_path / "m", episodes=100, progress=False,
                overrides=small("map"), device="cpu")
    settings = json.loads((run / "settings.json").read_text())
    with pytest.raises(CheckpointError, match="method"):
        load_checkpoint(run / "checkpoint.pt", expect={**settings, "method": "ibe_map", "n_ranges": 3})


def test_one_discount_env_gamma_drives_the_td_target(table, tmp_path, monkeypatch):
    """--set env.gamma=0.99 alone changes the TD target too; train.gamma differing from it
    is refused naming both values, before anything is written."""
    import uevavd.policy.trainer as trainer
    from uevavd.config import ConfigError

    seen = []

    class Spy(trainer.Learner):
        def __init__(self, *a, **kw):
            seen.append(kw["gamma"])
            super().__init__(*a, **kw)

    monkeypatch.setattr(trainer, "Learner", Spy)
    over = {**small("map"), "train.eval_splits": []}
    run = train(load_method("map"), table, out=tmp_path / "g", episodes=50, progress=False, device="cpu",
                overrides={**over, "env.gamma": 0.99})
    assert seen == [0.99]
    settings = json.loads((run / "settings.json").read_text())
    assert settings["train"]["gamma"] == settings["env"]["gamma"] == 0.99
    # both set and equal: accepted
    train(load_method("map"), table, out=tmp_path / "g2", episodes=50, progress=False, device="cpu",
          overrides={**over, "env.gamma": 0.95, "train.gamma": 0.95})
    assert seen[-1] == 0.95
    for bad in ({"env.gamma": 0.99, "train.gamma": 0.95}, {"train.gamma": 0.95}):
        with pytest.raises(ConfigError, match=r"train.gamma = 0.95 and env.gamma = 0.9\d?"):
            train(load_method("map"), table, out=tmp_path / "bad", episodes=50, progress=False, device="cpu",
                  overrides={**over, **bad})
        assert not (tmp_path / "bad").exists()


def test_max_epochs_stop_always_checkpoints(table, tmp_path):
    """A call stopped by max_epochs on an epoch that checkpoint_every skips still saves its
    work, and resuming it gives the straight run's weights."""
    spec = load_method("map")
    kw = dict(episodes=200, seed=1, progress=False, device="cpu",
              overrides={**small("map"), "train.checkpoint_every": 2, "train.eval_splits": ["train"]})
    straight = train(spec, table, out=tmp_path / "a", **kw)
    first = train(spec, table, out=tmp_path / "b", max_epochs=1, **kw)
    assert (first / "checkpoint.pt").is_file()
    assert load_checkpoint(first / "checkpoint.pt")["loop"]["epoch"] == 1
    resumed = train(spec, table, out=tmp_path / "b", **kw)
    assert load_checkpoint(resumed / "checkpoint.pt")["loop"]["episodes"] >= 200
    rows = [json.loads(line)["epoch"] for line in (resumed / "evals.jsonl").read_text().splitlines()]
    assert rows == [1, 2]
    wa, wb = _weights(straight), _weights(resumed)
    for k in wa:
        assert torch.equal(wa[k], wb[k]), k


@pytest.mark.parametrize("splits, missing", [(("hard", "hard"), "train"), (("train", "train"), "hard")])
def test_table_without_a_split_leaves_the_run_directory_untouched(tmp_path, splits, missing):
    from uevavd.table import TableError
    from uevavd.testing.policy import toy_table

    t = toy_table(n_train=2, n_hard=0, feature_dim=8)
    t = type(t).from_arrays(t.features, t.probs, t.boxes, scenes=list(t.scenes), targets=t.targets.tolist(),
                            splits=list(splits), contexts=t.contexts.tolist())
    empty = tmp_path / "empty"
    empty.mkdir()
    for out in (tmp_path / "absent", empty):
        with pytest.raises(TableError, match=rf"split '{missing}'.*{splits[0]}"):
            train(load_method("map"), t, out=out, episodes=50, progress=False, device="cpu",
                  overrides=small("map"))
    assert not (tmp_path / "absent").exists()
    assert list(empty.iterdir()) == []


def test_tensorboard_gets_update_diagnostics_and_the_settings(table, tmp_path, monkeypatch):
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    import uevavd.policy.trainer as trainer

    monkeypatch.setattr(trainer, "TB_EVERY_UPDATES", 5)
    run = train(load_method("map"), table, out=tmp_path / "tb", episodes=200, progress=False,
                overrides=small("map"), device="cpu")
    events = EventAccumulator(str(run / "tb")).Reload()
    tags = set(events.Tags()["scalars"])
    for tag in ("loss", "td_error", "mean_q", "grad_norm", "epsilon", "episodes_per_s"):
        assert f"update/{tag}" in tags, tag
    steps = [e.step for e in events.Scalars("update/td_error")]
    assert steps[:3] == [5, 10, 15] and all(e.value >= 0 for e in events.Scalars("update/td_error"))
    assert "settings/text_summary" in events.Tags()["tensors"]


def test_policy_file_of_another_method_or_action_space_is_refused_naming_it(table, tmp_path):
    import uevavd
    from uevavd.env.config import EnvConfig
    from uevavd.policy.checkpoint import check_policy_fits, save_policy_file

    run = train(load_method("map"), table, out=tmp_path / "m", episodes=100, progress=False,
                overrides=small("map"), device="cpu")
    path = run / "policy.safetensors"
    policy, cfg = uevavd.load_policy_file(path, table=table, method="map")
    assert cfg.max_range == 4 and policy.net is not None
    with pytest.raises(CheckpointError, match="method: the file holds 'map', not 'ibe_map'"):
        uevavd.load_policy_file(path, method="ibe_map")
    method_toml, settings, state = read_policy_file(path)
    with pytest.raises(CheckpointError, match="action space: the policy chooses among 4 ranges, the env config "
                                              "has max_range 3"):
        check_policy_fits(path, settings, env=EnvConfig(max_range=3))
    # a header that claims another action space than the network it carries: named, not torch's message
    forged = save_policy_file(tmp_path / "forged.safetensors", state, method_toml,
                              {**settings, "env": {**settings["env"], "max_range": 3}})
    with pytest.raises(CheckpointError, match=r"forged.safetensors: its network does not match the method it names \(shapes \(file vs network\): head"):
        uevavd.load_policy_file(forged)


def test_stand_in_table_with_simple_contexts_is_evaluated_on_them(tmp_path):
    """The stand-in of `benchmarks/bench_ablation.py` has the paper's three splits, and a run
    on it evaluates on all three as the paper preset asks."""
    from uevavd.testing.policy import SMALL_RUN, toy_table

    three = toy_table(4, 2, 8, n_simple=2)
    assert list(three.splits) == ["train"] * 4 + ["hard"] * 2 + ["simple"] * 2
    run = train(load_method("map"), three, out=tmp_path / "r", episodes=200, seed=0, progress=False, device="cpu",
                overrides={**SMALL_RUN, "train.eval_splits": ["train", "simple", "hard"]})
    rows = [json.loads(line) for line in (run / "evals.jsonl").read_text().splitlines()]
    assert {r["split"] for r in rows} == {"train", "simple", "hard"}


def test_train_restores_the_callers_torch_thread_count(table, tmp_path):
    """``train.threads`` holds for the run only: a library caller's own setting comes back
    after it (a notebook set to 2 threads stays on 2 after a 1-thread run)."""
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        run = train(load_method("map"), table, out=tmp_path / "t", episodes=100, progress=False,
                    overrides=small("map"), device="cpu")
        assert json.loads((run / "settings.json").read_text())["threads"] == 1  # trained on the run's count
        assert torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(before)


def test_a_run_trains_the_same_weights_whatever_the_callers_thread_count(table, tmp_path):
    """The weights depend on the torch thread count even at these sizes; a run used the
    caller's (torch's default: the machine's cores), so ``uevavd train`` on 2 cores trained
    other weights than the demo's 1-thread run of the same method, table and seed."""
    over = {k: v for k, v in small("map").items() if k != "train.threads"}  # the default count
    before = torch.get_num_threads()
    weights, recorded = [], []
    try:
        for caller in (1, 2):
            torch.set_num_threads(caller)
            run = train(load_method("map"), table, out=tmp_path / f"c{caller}", episodes=200, progress=False,
                        overrides=over, device="cpu")
            weights.append(_weights(run))
            recorded.append(json.loads((run / "settings.json").read_text())["threads"])
    finally:
        torch.set_num_threads(before)
    assert recorded == [1, 1]
    assert all(torch.equal(weights[0][k], weights[1][k]) for k in weights[0])


def test_train_leaves_the_callers_torch_random_stream_alone(table, tmp_path):
    """The run seeds torch's global RNG to initialise its network; a notebook's own stream
    continued from the run's seed afterwards. It is restored, and the run's weights do not
    depend on what the caller drew before."""
    over = small("map")
    torch.manual_seed(987)  # whatever ran before in the process
    before = torch.random.get_rng_state()
    first = train(load_method("map"), table, out=tmp_path / "a", episodes=100, progress=False, overrides=over,
                  device="cpu")
    assert torch.equal(torch.random.get_rng_state(), before)
    torch.rand(5)
    second = train(load_method("map"), table, out=tmp_path / "b", episodes=100, progress=False, overrides=over,
                   device="cpu")
    wa, wb = _weights(first), _weights(second)
    assert all(torch.equal(wa[k], wb[k]) for k in wa)
