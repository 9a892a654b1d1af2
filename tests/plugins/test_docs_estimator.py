"""The state estimator docs/architecture.md gives, written as a package from its three blocks
alone, passes `uevavd plugins --check` and trains: the protocol the docs state is the one the
library calls (``initial_hidden(n, device)``), and the checks ask for no key the docs do not
(the built-in GRU's ``box_dim`` and ``hidden``). Broken fast paths are refused before a run
writes anything."""

from __future__ import annotations

import re
import sys
from pathlib import Path

import pytest
import torch

DOCS = Path(__file__).resolve().parents[2] / "docs" / "architecture.md"


def _docs_package(root: Path) -> str:
    """Write the blocks under "A state estimator." as the files their first lines name."""
    text = DOCS.read_text(encoding="utf-8")
    section = text[text.index("**A state estimator.**"):text.index("**A method.**")]
    blocks = re.findall(r"```(?:python|toml)\n(.*?)```", section, flags=re.S)
    assert len(blocks) == 3, "docs/architecture.md's state estimator example is three blocks"
    for block in blocks:
        name = block.splitlines()[0].lstrip("# ").split(" ")[0]
        path = root / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(block, encoding="utf-8")
    return "my_pkg"


@pytest.fixture
def docs_plugin(tmp_path, monkeypatch):
    name = _docs_package(tmp_path)
    monkeypatch.syspath_prepend(str(tmp_path))
    yield name
    for mod in [m for m in sys.modules if m == name or m.startswith(name + ".")]:
        del sys.modules[mod]


def test_the_docs_estimator_passes_the_plugin_check_and_trains(docs_plugin, capsys):
    from uevavd.cli import main
    from uevavd.testing import check_plugin

    report = check_plugin(docs_plugin, presets=("quick",), episodes=200)
    assert any("memo_map_tiny: trained 200 toy episodes" in line for line in report.checked), report
    assert any("state tiny_gru" in line and "the rules" in line for line in report.checked), report
    assert main(["plugins", "--check", docs_plugin]) == 0
    assert "memo_map_tiny" in capsys.readouterr().out


class _Concat(torch.nn.Module):
    """A custom observation encoder: [features, box], without project / combine."""

    def forward(self, features, boxes):
        return torch.cat([features, boxes], -1)


class _Wrong(torch.nn.Module):
    """The built-in single-view estimator with a step_encoded that does something else."""

    recurrent = False

    def __init__(self, feature_dim: int, broken: str) -> None:
        super().__init__()
        from uevavd.state.base import ObservationEncoder

        self.feature_dim, self.state_dim, self.broken = feature_dim, 8, broken
        self.encoder = ObservationEncoder(feature_dim, 8, 4) if broken == "fast" else _Concat()
        self.out = torch.nn.Linear(12 if broken == "fast" else feature_dim + 4, 8)

    def initial_hidden(self, n, device="cpu"):
        return torch.zeros(n, 0, device=device)

    def forward(self, features, boxes):
        return torch.relu(self.out(self.encoder(features, boxes)))

    def step(self, features, boxes, hidden):
        return self(features[:, None], boxes[:, None])[:, 0], hidden

    def step_encoded(self, g, hidden):
        return torch.relu(self.out(g)) * 2.0, hidden  # not what step gives


@pytest.mark.parametrize("broken, needle", [
    ("fast", "disagrees with step()"),
    ("encoder", "its encoder has no 'image_dim'"),
])
def test_a_wrong_fast_path_is_refused_before_the_run_writes_anything(broken, needle, tmp_path):
    """A wrong step_encoded trained through step and was scored through itself (hard -0.079
    against -0.039); one over a custom encoder wrote method.toml, settings.json and tb/, then
    raised an AttributeError in the first evaluation."""
    from uevavd.policy.contract import ComponentError, check_estimator_rules

    with pytest.raises(ComponentError, match=re.escape(needle)):
        check_estimator_rules(_Wrong(16, broken), feature_dim=16)
