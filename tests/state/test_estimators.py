import pytest

from uevavd.config import load_method
from uevavd.plugins.manager import manager
from uevavd.testing import check_head, check_state_estimator


@pytest.mark.parametrize("name", manager.registry.names("state"))
def test_registered_state_estimators_meet_the_contract(name):
    est = manager.registry.build("state", name, feature_dim=8, input_dim=24, box_dim=8, state_dim=12)
    check_state_estimator(est)


@pytest.mark.parametrize("name", manager.registry.names("head"))
def test_registered_heads_meet_the_contract(name):
    check_head(manager.registry.build("head", name, state_dim=12, hidden=8))


def test_paper_sizes():
    spec = load_method("memo_map")
    est = spec.build("state", feature_dim=2048)
    assert est.encoder.out_dim == 544 and est.hidden_dim == 544 and est.state_dim == 512


def test_bad_sizes_are_refused():
    with pytest.raises(ValueError, match="box_dim"):
        manager.registry.build("state", "gru", feature_dim=8, input_dim=8, box_dim=8)


def test_gru_hidden_follows_input_dim_unless_set():
    """h_t has g_t's size by default (paper: 544 = 544), so one override scales both."""
    est = load_method("memo_map", overrides={"state.input_dim": 160}).build("state", feature_dim=64)
    assert est.hidden_dim == 160 and est.encoder.out_dim == 160
    est = load_method("memo_map", overrides={"state.hidden": 96}).build("state", feature_dim=64)
    assert est.hidden_dim == 96
