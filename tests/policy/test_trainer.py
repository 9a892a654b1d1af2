import json

import pytest
import torch

from uevavd.config import load_method
from uevavd.policy.agent import load_policy
from uevavd.policy.checkpoint import CheckpointError, load_checkpoint
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
    resumed = train(spec, table, out=tmp_path / "b", **kw)
    assert (resumed / "done.json").exists()
    wa, wb = _weights(straight), _weights(resumed)
    assert wa.keys() == wb.keys()
    for k in wa:
        assert torch.equal(wa[k], wb[k]), k
    rows = [json.loads(line) for line in (resumed / "evals.jsonl").read_text().splitlines()]
    assert [(r["epoch"], r["split"]) for r in rows] == [(1, "train"), (1, "hard"), (2, "train"), (2, "hard")]
    # a finished run returns at once; another configuration is refused, naming the difference
    assert train(spec, table, out=tmp_path / "b", **kw) == resumed
    with pytest.raises(RunDirError, match="seed"):
        train(spec, table, out=tmp_path / "b", **{**kw, "seed": 4})
    from uevavd.env.evaluate import evaluate_policy
    from uevavd.policy.agent import GreedyPolicy

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
