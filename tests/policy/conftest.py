import pytest
import torch

from uevavd.testing.policy import toy_table

SMALL = {
    "state.input_dim": 24, "state.box_dim": 8, "state.state_dim": 16,
    "head.hidden": 16, "train.n_envs": 16, "train.batch_size": 8, "train.buffer_episodes": 400,
    "train.learning_starts": 40, "train.updates_per_step": 1.0, "train.target_update": 5,
    "train.epoch_episodes": 100, "train.eval_contexts": 1, "train.threads": 1,
}


@pytest.fixture(scope="session")
def table():
    torch.set_num_threads(1)
    return toy_table(n_train=3, n_hard=2, feature_dim=8)


def small(method: str) -> dict:
    out = dict(SMALL)
    if method != "map":
        out["state.hidden"] = 16
    return out
