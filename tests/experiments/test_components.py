"""Component ablations: the precedence rule (shipped methods < a preset's [overrides] < your
method files < --set < --sweep), method files by path, perception keys as sweep axes (each value
its own table), crossed axes, and the report's paired differences of every arm against the
default, through ``uevavd.ablate`` on the 16 px test world."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

import uevavd
from uevavd.cli import main
from uevavd.config import load_method
from uevavd.experiments.plan import AblationError, make_plan, parse_sweeps
from uevavd.experiments.runner import check_out_dir
from uevavd.presets import load_preset, preset_dir, preset_overrides
from uevavd.testing.worlds import tiny_preset

QUICK = preset_overrides(load_preset("quick"))
#: A researcher's own variant of IBE-MAP: another encoder, and a narrower state.
IBE_R18 = """name = "ibe_r18"
_base_ = "ibe_map"

[perception]
encoder = { name = "resnet18", weights = "random" }

[state]
state_dim = 64
"""


@pytest.fixture
def ibe_r18(tmp_path) -> Path:
    path = tmp_path / "ibe_r18.toml"
    path.write_text(IBE_R18)
    return path


def test_a_method_file_keeps_the_encoder_it_names_under_a_preset(ibe_r18, tmp_path):
    """The quick preset substitutes EfficientNet-Lite0 for the shipped methods' ResNet50, but never
    for the encoder a user's file names: the run uses ResNet18 from random weights."""
    plan = make_plan(preset="quick", out=tmp_path / "out", methods=["ibe_map", str(ibe_r18)])
    assert plan.methods == ["ibe_map", "ibe_r18"]
    mine = plan.spec("ibe_r18")
    assert dict(mine.get("perception.encoder")) == {"name": "resnet18", "weights": "random"}
    assert mine.get("state.state_dim") == 64 and mine.get("state.input_dim") == 160  # its key; the preset's width
    assert any("perception.encoder.name" in n for n in mine.preset_notes)
    # the shipped methods resolve exactly as before: the preset's components and widths
    for m in ("map", "memo_map", "ibe_map", "ibe_map_pose"):
        assert load_method(m, preset=QUICK).hash == load_method(m, overrides=QUICK).hash
    assert plan.spec("ibe_map").get("perception.encoder.name") == "efficientnet_lite0"
    assert plan.components("ibe_r18")["perception.encoder"] == {"name": "resnet18", "weights": "random"}
    # --set is the command line: it wins over the method file
    plan = make_plan(preset="quick", out=tmp_path / "out2", methods=[str(ibe_r18)], sets={"state.state_dim": 32})
    assert plan.spec("ibe_r18").get("state.state_dim") == 32


def test_a_presets_ablation_names_method_files_from_its_own_folder(ibe_r18, tmp_path):
    preset = tmp_path / "mine.toml"
    preset.write_text((preset_dir() / "quick.toml").read_text().split("[ablation]")[0]
                      + '[ablation]\nmethods = ["ibe_map", "ibe_r18.toml"]\nsweep_methods = ["ibe_r18.toml"]\n')
    plan = make_plan(preset=str(preset), out=tmp_path / "o", sweeps=parse_sweeps(["train.lr=3e-3"]))
    assert plan.methods == ["ibe_map", "ibe_r18"] and plan.sweep_methods == ["ibe_r18"]
    assert plan.method_files == {"ibe_r18": str(ibe_r18.resolve())}


def test_a_swept_component_name_switches_its_arguments_with_it(tmp_path):
    """--sweep perception.encoder.name=resnet18 under quick: ResNet18 with its own defaults, never
    the preset's EfficientNet arguments; a whole section gives the arguments; the default value
    runs once."""
    plan = make_plan(preset="quick", out=tmp_path / "o", methods=["ibe_map"], sweep_methods=["ibe_map"],
                     sweeps=parse_sweeps(["perception.encoder.name=efficientnet_lite0,resnet18"]))
    names = [n for n, _ in plan.settings("ibe_map")]
    assert names == ["default", "perception.encoder.name=resnet18"]
    setting = dict(plan.settings("ibe_map"))["perception.encoder.name=resnet18"]
    assert dict(plan.spec("ibe_map", setting).get("perception.encoder")) == {"name": "resnet18"}
    sweeps = parse_sweeps(['perception.encoder={name="resnet18",weights="random"},{name="resnet50",weights="random"}',
                           "perception.decompose=true,false"])
    assert sweeps["perception.encoder"][1] == {"name": "resnet50", "weights": "random"}
    plan = make_plan(preset="quick", out=tmp_path / "p", methods=["ibe_map"], sweep_methods=["ibe_map"], sweeps=sweeps)
    assert [n for n, _ in plan.settings("ibe_map")] == [
        "default", "perception.encoder=resnet18(weights=random)", "perception.encoder=resnet50(weights=random)",
        "perception.decompose=false"]


def test_crossed_axes_give_the_factorial_and_keep_the_presets_widths(tmp_path):
    """State estimator x views on IBE-MAP: its four corners, the single-view state at the preset's
    widths (the preset scales every state estimator, whichever a sweep picks)."""
    plan = make_plan(preset="quick", out=tmp_path / "f", methods=["ibe_map"], sweep_methods=["ibe_map"], cross=True,
                     sweeps=parse_sweeps(["state.name=single_view,gru", "perception.decompose=false,true"]))
    settings = dict(plan.settings("ibe_map"))
    assert list(settings) == ["default", "state.name=single_view", "perception.decompose=false",
                              "state.name=single_view+perception.decompose=false"]
    corner = plan.spec("ibe_map", settings["state.name=single_view+perception.decompose=false"])
    assert dict(corner.get("state")) == {"name": "single_view", "input_dim": 160, "state_dim": 128}
    assert corner.get("perception.decompose") is False
    # MAP's own spec is the same network on the same views
    assert dict(load_method("map", preset=QUICK).get("state")) == {**corner.get("state"), "box_dim": 32}


@pytest.mark.parametrize("kwargs, message", [
    ({"methods": ["ibe_map", "IBE"]}, r"method file .*IBE\.toml does not exist"),
    ({"sets": {"env.thre": 0.3}, "sweeps": {"env.thre": [0.2, 0.4]}}, "name the same key"),
    ({"methods": ["map", "map"]}, "given twice"),
])
def test_bad_component_ablations_are_refused_in_one_line(tmp_path, kwargs, message):
    if kwargs.get("methods") == ["ibe_map", "IBE"]:
        kwargs = {"methods": ["ibe_map", str(tmp_path / "IBE.toml")]}
    with pytest.raises(AblationError, match=message):
        make_plan(preset="quick", out=tmp_path / "x", sweep_methods=["map"] if "sweeps" in kwargs else None,
                  **({"methods": ["map"]} | kwargs))


def test_a_method_file_named_like_a_registered_method_is_refused(tmp_path):
    path = tmp_path / "mine.toml"
    path.write_text('name = "ibe_map"\n_base_ = "ibe_map"\n')
    with pytest.raises(AblationError, match=r"named 'ibe_map', like a registered method: give it its own `name`"):
        make_plan(preset="quick", out=tmp_path / "x", methods=[str(path)])


def test_an_edited_method_file_is_another_ablation(ibe_r18, tmp_path):
    plan = make_plan(preset="quick", out=tmp_path / "out", methods=[str(ibe_r18)])
    plan.out.mkdir()
    (plan.out / "ablation.json").write_text("{}")  # replaced below by the runner's own writer
    from uevavd.experiments.runner import write_meta

    write_meta(plan, None, "training")
    check_out_dir(make_plan(preset="quick", out=tmp_path / "out", methods=[str(ibe_r18)]))  # the same file: resumes
    ibe_r18.write_text(IBE_R18.replace("64", "96"))
    with pytest.raises(AblationError, match=r"another configuration \(differs in \['method_files'\]\)"):
        check_out_dir(make_plan(preset="quick", out=tmp_path / "out", methods=[str(ibe_r18)]))


@pytest.mark.parametrize("sweep, message", [
    # a decomposition without masks: every view one flat gray
    ("perception.segmenter.name=gt,none",
     "method 'ibe_map' at perception.segmenter.name=none: perception.decompose = true with segmenter 'none'"),
    # ResNet50 with ImageNet weights that this machine lacks (TORCH_HOME below holds none)
    ("perception.encoder.name=resnet50", "method 'ibe_map' at perception.encoder.name=resnet50: perception.encoder "
                                         "'resnet50'"),
])
def test_a_component_that_cannot_be_built_is_refused_before_any_work(tmp_path, capsys, monkeypatch, sweep, message):
    """One line naming the method, the setting and the cause, before the world or ablation.json
    is written (it failed at the tables stage, 100-230 s in)."""
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "torch"))
    out = tmp_path / "out"
    rc = main(["ablate", "--preset", "quick", "--methods", "ibe_map", "--sweep", sweep, "--out", str(out)])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1, err
    assert message in err[0]
    assert not out.exists()


@pytest.fixture(scope="module")
def encoder_ablation(tmp_path_factory, ablation_world):
    """IBE-MAP against its own variant with a random ResNet18 encoder, through the Python API."""
    root = tmp_path_factory.mktemp("components")
    preset = root / "tiny.toml"
    preset.write_text(tiny_preset(episodes=100, ablation='methods = ["ibe_map"]\nseeds = 2\n'))
    lines: list[str] = []
    abl = uevavd.ablate(out=root / "out", preset=preset, data=ablation_world, workers=1, figures=False,
                        sweep={"perception.encoder": [{"name": "resnet18", "weights": "random"}]},
                        sweep_methods=["ibe_map"], log=lines.append)
    return {"ablation": abl, "log": lines, "preset": preset, "world": ablation_world}


def test_an_encoder_arm_builds_its_own_table_and_is_compared_paired(encoder_ablation):
    abl = encoder_ablation["ablation"]
    df = abl.results
    arm = "perception.encoder=resnet18(weights=random)"
    assert set(df.loc[df["method"] == "ibe_map", "setting"]) == {"default", arm}
    assert set(df.loc[df["setting"] == arm, "perception.encoder"]) == {"resnet18(weights=random)"}
    assert any(f"ibe_map at {arm}: table" in x for x in encoder_ablation["log"])  # a table of its own
    tables = {json.loads((r / "settings.json").read_text())["table_key"]
              for r in (abl.path / "runs" / "ibe_map").glob("*/rec0/seed0")}
    assert len(tables) == 2
    comps = abl.components["ibe_map"]
    assert comps[arm]["perception.encoder"] == {"name": "resnet18", "weights": "random"}
    assert comps["default"]["perception.encoder"] == {"name": "resnet18", "weights": "classifier"}
    diffs = abl.differences()
    ret = diffs[(diffs["metric"] == "return") & (diffs["split"] == "hard") & (diffs["terrain"] == "all")]
    assert len(ret) == 1 and ret["n"].iloc[0] == 2
    final = abl.final()
    hard = final[(final["split"] == "hard") & (final["method"] == "ibe_map")].set_index(["setting", "seed"])["return"]
    want = np.mean([hard[(arm, s)] - hard[("default", s)] for s in (0, 1)])
    assert ret["difference"].iloc[0] == pytest.approx(want)
    assert ret["lo"].iloc[0] <= want <= ret["hi"].iloc[0]
    report = abl.report.read_text()
    assert "## Arms against the default" in report and f"`{arm}`" in report
    assert "Perception of IBE-MAP at `perception.encoder=resnet18(weights=random)`: encoder resnet18 (random)" in report
    assert pd.read_csv(abl.report.parent / "arms.csv")["setting"].eq(arm).all()


def test_run_curve_reads_the_learning_curve(encoder_ablation):
    run = uevavd.load_run(encoder_ablation["ablation"].path / "runs" / "ibe_map" / "default" / "rec0" / "seed0")
    curve = run.curve()
    assert curve["episodes"].nunique() == 1 and curve["episodes"].iloc[0] >= 100  # one epoch of 100 episodes
    assert set(curve["split"]) == {"train", "hard"}
    assert {"return", "accuracy", "recognition", "path_m"} <= set(curve.columns)
    frame = run.evaluate("hard", baselines=False)  # the shape evaluate_pretrained returns too
    assert list(frame.index) == ["ibe_map"] and list(frame.attrs["per_context"]["context"]) == [26, 56]


def test_two_ablations_merge_into_one_report(encoder_ablation, tmp_path, capsys):
    """A second day's arm (a single-view state) beside the first day's encoder arm: one results
    table, one arms section; the shared default arm is kept once. Another evaluation is refused."""
    first = encoder_ablation["ablation"]
    second = uevavd.ablate(out=tmp_path / "day2", preset=encoder_ablation["preset"], data=encoder_ablation["world"],
                           workers=1, figures=False, sweep={"state.name": ["single_view"]},
                           sweep_methods=["ibe_map"], log=lambda *_: None)
    out = tmp_path / "both"
    assert main(["report", str(first.path), str(second.path), "--out", str(out), "--no-figures"]) == 0
    merged = uevavd.api.Ablation(out)
    settings = set(merged.results.loc[merged.results["method"] == "ibe_map", "setting"])
    assert settings == {"default", "perception.encoder=resnet18(weights=random)", "state.name=single_view"}
    assert len(merged.results) == len(first.results) + len(second.results) - len(
        second.results[(second.results["method"] == "ibe_map") & (second.results["setting"] == "default")]) - len(
        second.results[second.results["episodes"] < 0])
    assert set(merged.differences()["setting"]) == settings - {"default"}
    assert "`state.name=single_view`" in merged.report.read_text()
    assert main(["report", str(first.path), str(second.path)]) == 2
    assert "merge them into one report with --out DIR" in capsys.readouterr().err
    results = pd.read_csv(second.path / "results.csv")
    results.loc[results["method"] == "passive", "return"] += 0.01
    results.to_csv(second.path / "results.csv", index=False)
    assert main(["report", str(first.path), str(second.path), "--out", str(tmp_path / "bad")]) == 2
    assert "results.csv: not the table the ablation wrote" in capsys.readouterr().err
    from uevavd.atomic import write_sealed_json
    from uevavd.experiments.io import output_digests, read_ablation_meta

    meta = read_ablation_meta(second.path / "ablation.json")  # as if evaluated under another reward
    write_sealed_json(second.path / "ablation.json", {**meta, "outputs": output_digests(second.path)})
    assert main(["report", str(first.path), str(second.path), "--out", str(tmp_path / "bad")]) == 2
    assert "evaluate otherwise: their baselines' final rows differ" in capsys.readouterr().err


@pytest.mark.parametrize("cut", ["row", "field"])
def test_a_cut_results_table_is_refused_by_the_report(encoder_ablation, tmp_path, capsys, cut):
    """results.csv cut at a row boundary, or inside a row's last field (which keeps its field
    count), was reported from the rows left: ablation.json seals both tables now."""
    import shutil

    folder = tmp_path / "copy"
    shutil.copytree(encoder_ablation["ablation"].path, folder)
    text = (folder / "results.csv").read_text()
    lines = text.splitlines(keepends=True)
    (folder / "results.csv").write_text("".join(lines[:-5]) if cut == "row" else text[:-3])
    assert main(["report", str(folder), "--no-figures"]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "results.csv: not the table the ablation wrote" in err


def test_a_method_files_own_reward_constant_is_its_default_setting(tmp_path):
    """env.thre set in a user's method file was replaced by the paper's 0.2 in every default run;
    a sweep of thre still sets it (the command line wins)."""
    path = tmp_path / "strict.toml"
    path.write_text('name = "ibe_strict"\n_base_ = "ibe_map"\n[env]\nthre = 0.5\n')
    plan = make_plan(preset="quick", out=tmp_path / "o", methods=[str(path)], sweeps=parse_sweeps(["thre=0.4"]),
                     sweep_methods=[str(path)])
    settings = dict(plan.settings("ibe_strict"))
    assert plan.spec("ibe_strict").env.thre == 0.5
    assert plan.spec("ibe_strict", settings["thre=0.4"]).env.thre == 0.4
