import pytest
import torch

from uevavd.testing.policy import small_run as small  # noqa: F401  (the tests' import)
from uevavd.testing.policy import toy_table


@pytest.fixture(scope="session")
def table():
    torch.set_num_threads(1)
    return toy_table(n_train=3, n_hard=2, feature_dim=8)
