"""Method configs: inheritance, overrides, validation errors, hash, save and load back.

Components come from a test plugin registered in a fixture (and always unregistered).
"""

from __future__ import annotations

import textwrap
import types
from typing import Literal

import pytest

from uevavd.config import ConfigError, load_method, parse_override
from uevavd.plugins import hookimpl
from uevavd.plugins.manager import manager


def build_tstate(*, hidden: int = 8, layers: int = 1, kind: Literal["a", "b"] = "a", dropout: float = 0.0):
    return ("tstate", hidden, layers, kind, dropout)


def build_thead(*, hidden: int = 4, dueling: bool = True):
    return ("thead", hidden, dueling)


@pytest.fixture
def components():
    @hookimpl
    def register_state_estimators(registry):
        registry.add("tstate", f"{__name__}:build_tstate")
        registry.add("tstate2", f"{__name__}:build_thead")

    @hookimpl
    def register_heads(registry):
        registry.add("thead", f"{__name__}:build_thead")

    plug = types.SimpleNamespace(register_state_estimators=register_state_estimators, register_heads=register_heads)
    manager.register_plugin(plug, name="config-test-plugin")
    yield
    manager.unregister_plugin("config-test-plugin")


def write(tmp_path, name, text):
    p = tmp_path / f"{name}.toml"
    p.write_text(textwrap.dedent(text))
    return p


@pytest.fixture
def base(tmp_path, components):
    write(tmp_path, "base", """
        name = "base"
        description = "a base method"
        [state]
        name = "tstate"
        hidden = 16
        [head]
        name = "thead"
    """)
    return write(tmp_path, "child", """
        _base_ = "base.toml"
        name = "child"
        [state]
        layers = 2
    """)


def test_inheritance_changes_only_what_differs(base):
    spec = load_method(base)
    assert spec.name == "child"
    assert spec.component("state") == ("tstate", {"hidden": 16, "layers": 2})
    assert spec.component("head") == ("thead", {})
    assert spec.build("state", kind="b") == ("tstate", 16, 2, "b", 0.0)
    assert "description" not in spec.to_dict()  # a child does not inherit its base's description


def test_spec_is_frozen_and_hash_is_stable(base, tmp_path):
    spec = load_method(base)
    with pytest.raises(TypeError):
        spec.data["state"]["hidden"] = 3
    with pytest.raises(AttributeError):
        spec.name = "x"
    assert load_method(base).hash == spec.hash
    saved = spec.save(tmp_path / "run" / "method.toml")
    again = load_method(saved)
    assert again.hash == spec.hash and again.to_dict() == spec.to_dict()
    assert load_method(base, overrides={"state.hidden": 17}).hash != spec.hash


def test_overrides(base):
    spec = load_method(base, overrides={"state.hidden": 32, "head.dueling": False})
    assert spec["state.hidden"] == 32 and spec["head.dueling"] is False
    # switching the component drops the old builder's arguments
    spec = load_method(base, overrides={"state.name": "tstate2"})
    assert spec.component("state") == ("tstate2", {})
    assert parse_override("state.hidden=256") == ("state.hidden", 256)


@pytest.mark.parametrize("order", ["name last", "name first"])
def test_overrides_are_order_independent(order):
    """`--set perception.encoder.weights=X --set perception.encoder.name=Y` used to drop X:
    the name switch, applied last, wiped the arguments set before it."""
    items = [("perception.encoder.weights", "classifier"), ("perception.encoder.name", "resnet18")]
    if order == "name first":
        items.reverse()
    spec = load_method("map", overrides=dict(items))
    assert spec["perception.encoder.name"] == "resnet18"
    assert spec["perception.encoder.weights"] == "classifier"
    again = load_method("map").with_overrides(dict(items))  # the spec method: the same rule
    assert again.hash == spec.hash
    # a switch alone still drops what the old builder took (map's resnet50 weights)
    assert "weights" not in load_method("map", overrides={"perception.encoder.name": "resnet18"}).to_dict()[
        "perception"]["encoder"]
    assert parse_override("head.dueling=false") == ("head.dueling", False)
    assert parse_override("state.kind=b") == ("state.kind", "b")


def test_unknown_key_lists_accepted_and_suggests(base):
    with pytest.raises(ConfigError) as exc:
        load_method(base, overrides={"state.hiden": 3})
    msg = str(exc.value)
    assert "'hiden'" in msg and "'hidden'" in msg and "layers" in msg and "did you mean 'hidden'" in msg
    with pytest.raises(ConfigError, match="unknown key 'stat'.*did you mean 'state'"):
        load_method(base, overrides={"stat.hidden": 3})


@pytest.mark.parametrize(
    "key, value, expected",
    [("state.hidden", "big", "expected int"), ("state.hidden", 2.5, "expected int"),
     ("state.kind", "c", "expected one of 'a', 'b'"), ("head.dueling", 1, "expected bool"), ("state.dropout", "x", "expected float")],
)
def test_wrong_types(base, key, value, expected):
    with pytest.raises(ConfigError, match=expected):
        load_method(base, overrides={key: value})


def test_ints_are_accepted_for_floats(base):
    assert load_method(base, overrides={"state.dropout": 0})["state.dropout"] == 0


def test_unknown_component_and_missing_file(base, tmp_path):
    with pytest.raises(ConfigError, match="unknown state 'tstat'.*did you mean 'tstate'"):
        load_method(base, overrides={"state.name": "tstat"})
    with pytest.raises(ConfigError, match="does not exist"):
        load_method(tmp_path / "nope.toml")
    with pytest.raises(ConfigError, match="unknown method"):
        load_method("no_such_method")
    # a missing _base_ names the file holding it (it named only the missing method)
    write(tmp_path, "child", '_base_ = "missing.toml"\nname = "child"\n')
    with pytest.raises(ConfigError, match=r"child.toml: _base_ = 'missing.toml': method file .*missing.toml does not"):
        load_method(tmp_path / "child.toml")


def test_inheritance_loop_and_bad_toml(tmp_path, components):
    write(tmp_path, "a", '_base_ = "b.toml"\nname = "a"\n')
    write(tmp_path, "b", '_base_ = "a.toml"\nname = "b"\n')
    with pytest.raises(ConfigError, match="loops"):
        load_method(tmp_path / "a.toml")
    write(tmp_path, "bad", "name = \n")
    with pytest.raises(ConfigError, match="bad.toml: not valid TOML"):
        load_method(tmp_path / "bad.toml")


def test_a_setting_the_pipeline_passes_itself_is_refused():
    """state.feature_dim was accepted and then replaced by the table's feature size."""
    from uevavd.config import ConfigError, load_method

    with pytest.raises(ConfigError, match="state.feature_dim = 64 is not a setting: it comes from the table's"):
        load_method("map", overrides={"state.feature_dim": 64})


def test_a_config_error_with_many_overrides_is_a_short_line_naming_the_key():
    """Each config error line started with the whole overrides dict (about 1,500 characters
    under the toy-training overrides)."""
    from uevavd.testing.policy import small_run

    with pytest.raises(ConfigError) as err:
        load_method("memo_map", overrides={**small_run("memo_map"), "state.hiden": 3})
    text = str(err.value)
    assert "memo_map.toml with 15 overrides: unknown key state.'hiden'" in text and len(text) < 400, text
