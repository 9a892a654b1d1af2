"""The ablation runner end to end on the 16 px test world: a few hundred episodes per run.

One module-scoped ablation (MAP and IBE-MAP, one seed) is shared by the tests below; one of
its runs is interrupted by hand before the ablation starts, so the ablation must finish it.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch

from uevavd.cli import main
from uevavd.experiments.jobs import plan_jobs
from uevavd.experiments.plan import AblationError, make_plan, parse_sweeps
from uevavd.experiments.results import RESULT_COLUMNS, final_eval, is_done
from uevavd.experiments.runner import run_ablation, write_meta
from uevavd.experiments.stages import stage_classifier, stage_tables, stage_world
from uevavd.experiments.trajectories import pick_trajectory_start
from uevavd.policy.rundir import RunDir
from uevavd.testing.worlds import tiny_preset, write_tiny_world

TINY_PRESET = tiny_preset(ablation='methods = ["map", "ibe_map"]\nseeds = 1\n')


@pytest.fixture(scope="module")
def tiny(tmp_path_factory, ablation_world) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("ablation")
    preset = root / "tiny.toml"
    preset.write_text(TINY_PRESET)
    return {"root": root, "preset": preset, "world": ablation_world}


def _plan(tiny, out: str, **kw):
    return make_plan(preset=str(tiny["preset"]), out=tiny["root"] / out, data=tiny["world"], workers=1, **kw)


@pytest.fixture(scope="module")
def ablation(tiny) -> dict:
    """Interrupt one run after its first epoch, then run the whole ablation."""
    from uevavd.config import load_method
    from uevavd.policy.trainer import train

    plan = _plan(tiny, "out")
    data = stage_world(plan, print)
    tables = stage_tables(plan, data, stage_classifier(plan, data, print), print)
    plan.out.mkdir(parents=True)
    write_meta(plan, data, "training")  # as an ablation killed during training leaves it
    jobs = plan_jobs(plan, tables)
    interrupted = next(j for j in jobs if j.method == "ibe_map")
    train(load_method(interrupted.spec_path), Path(interrupted.table), out=Path(interrupted.out), seed=0,
          device="cpu", progress=False, max_epochs=1)  # on the method's thread count, as the ablation's runs
    assert not is_done(interrupted)
    partial_epochs = len(Path(interrupted.out, "evals.jsonl").read_text().splitlines())

    lines: list[str] = []
    plan = _plan(tiny, "out", figures=False)  # the figures' drawing is test_report.py's; the default is checked below
    results = run_ablation(plan, log=lines.append)
    return {"plan": plan, "results": results, "log": lines, "interrupted": interrupted,
            "partial_epochs": partial_epochs, "jobs": jobs}


def test_results_are_tidy_and_complete(ablation):
    df = pd.read_csv(ablation["results"])
    assert list(df.columns) == RESULT_COLUMNS
    assert set(df["method"]) == {"map", "ibe_map", "random", "passive", "box_gate", "pose_seek", "departure_ceiling",
                                "departure_ceiling2", "visibility_oracle", "oracle"}
    assert set(df["split"]) == {"train", "hard"}
    for method in ("map", "ibe_map"):
        rows = df[df["method"] == method]
        # two evaluation points (epochs end at the first batch past 100 and 200 episodes) x two
        # splits, the last ones final
        points = sorted(rows["episodes"].unique())
        assert len(points) == 2 and 100 <= points[0] < 200 <= points[1] < 250
        assert rows[rows["final"]]["episodes"].eq(points[1]).all() and rows["final"].sum() == 2
        # the curve (per epoch, train.eval_contexts = 1 context) and the exhaustive final rows
        # (both contexts of each split, as the baselines)
        assert rows.loc[~rows["final"], "eval_contexts"].eq(1).all() and len(rows[~rows["final"]]) == 4
        assert rows.loc[rows["final"], "eval_contexts"].eq(2).all()
    assert df.loc[df["episodes"] < 0, "eval_contexts"].eq(2).all()
    assert df[["return", "accuracy", "recognition", "path_m"]].notna().all().all()


def test_final_rows_are_the_exhaustive_evaluation_of_the_final_policy(ablation):
    """Every context x 605 starts under the run's env config, cached in final_eval.json."""
    from uevavd.env.config import EnvConfig
    from uevavd.env.evaluate import evaluate_policy
    from uevavd.policy.acting import load_policy

    df = pd.read_csv(ablation["results"])
    for job in ablation["jobs"]:
        cached = json.loads(RunDir(job.out).final_eval.read_text())
        assert cached["key"]["env"]["thre"] == 0.2 and cached["key"]["splits"] == ["train", "hard"]
        for split in ("train", "hard"):
            res = evaluate_policy(job.table, split, load_policy(job.out), EnvConfig(thre=0.2, C=0.02))
            assert len(res) == 2 * 605
            row = df[(df["method"] == job.method) & df["final"] & (df["split"] == split)].iloc[0]
            assert row["return"] == pytest.approx(res.summary()["mean_return"], abs=1e-9)
            assert row["recognition"] == pytest.approx(res.summary()["recognition_rate"], abs=1e-9)


def test_final_eval_is_recomputed_when_missing_or_stale(ablation, tmp_path):
    """A run copied with another env config (the C=0 / thre=0.6 setting's) is evaluated under
    that config, not the default; a missing or stale cache is rebuilt, a valid one reused."""
    import dataclasses
    import shutil

    from uevavd.env.config import EnvConfig
    from uevavd.env.evaluate import evaluate_policy
    from uevavd.policy.acting import load_policy

    job = ablation["jobs"][0]
    copy = dataclasses.replace(job, out=str(tmp_path / "run"))
    shutil.copytree(job.out, copy.out)
    from uevavd.policy.rundir import read_done, read_settings, write_done, write_settings

    settings = read_settings(copy.out)
    settings["env"].update(thre=0.6, C=0.0)
    write_settings(copy.out, settings)  # as a run of that setting records it: its mark on done.json, its
    write_done(copy.out, settings, read_done(job.out))  # env in the checkpoint
    ck = torch.load(RunDir(copy.out).checkpoint, weights_only=True)
    ck["meta"]["env"].update(thre=0.6, C=0.0)
    torch.save(ck, RunDir(copy.out).checkpoint)
    first = final_eval(copy)  # the copied cache holds the default config: stale
    assert first["key"]["env"]["thre"] == 0.6
    want = evaluate_policy(copy.table, "hard", load_policy(copy.out), EnvConfig(thre=0.6, C=0.0)).summary()
    assert first["splits"]["hard"]["mean_return"] == pytest.approx(want["mean_return"], abs=1e-9)
    assert first["splits"]["hard"]["recognition_rate"] == pytest.approx(want["recognition_rate"], abs=1e-9)
    mtime = RunDir(copy.out).final_eval.stat().st_mtime_ns
    assert final_eval(copy) == first and RunDir(copy.out).final_eval.stat().st_mtime_ns == mtime  # reused
    RunDir(copy.out).final_eval.unlink()
    assert final_eval(copy) == first  # recomputed, same numbers
    assert not list(Path(copy.out).glob(f".{RunDir(copy.out).final_eval.name}.*"))  # atomic write, no temp left


def test_workers_default_to_the_number_of_cores(tiny, monkeypatch):
    import os

    # 7 cores to run on (raising=False: an OS without the affinity call gets it too)
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: set(range(7)), raising=False)
    assert make_plan(preset=str(tiny["preset"]), out=tiny["root"] / "w", data=tiny["world"]).workers == 7
    assert make_plan(preset=str(tiny["preset"]), out=tiny["root"] / "w", data=tiny["world"], workers=3).workers == 3


def _one_hard_scene(good_views, visible):
    """A table of one hard-test scene (hatchback) recognised only at ``good_views``."""
    from uevavd.table import ObservationTable

    probs = np.full((1, 605, 5), 0.2375, np.float32)
    probs[0, :, 0] = 0.05
    probs[0, good_views] = [0.9, 0.025, 0.025, 0.025, 0.025]
    return ObservationTable.from_arrays(
        np.zeros((1, 605, 4)), probs, np.full((1, 605, 4), 0.5), scenes=["026"], targets=[0],
        splits=["hard"], contexts=[26], visible=np.asarray(visible, np.float32)[None])


def test_trajectory_start_passive_fails_and_oracle_succeeds():
    """The least visible failing view (the far corner) cannot reach the one recognised view
    (a corner) in 5 moves of at most 4 grid steps: it is not picked."""
    from uevavd.env.config import EnvConfig
    from uevavd.env.evaluate import evaluate_policy
    from uevavd.env.oracle import OraclePolicy

    config = EnvConfig()
    table = _one_hard_scene([0], visible=1.0 - np.arange(605) / 605)
    scene, start = pick_trajectory_start(table, config)
    assert (scene, start) == pick_trajectory_start(table, config)  # deterministic
    assert start != 604 and not config.recognized(table.true_class_probs())[scene, start]  # passive fails
    res = evaluate_policy(table, "hard", OraclePolicy(table, config), config)
    i = int(np.flatnonzero((res.scene == scene) & (res.start_view == start))[0])
    assert res.recognized[i] and res.final_view[i] == 0  # the oracle's episode ends recognised
    reachable = res.recognized & ~config.recognized(table.true_class_probs())[0]
    assert start == int(np.flatnonzero(reachable).max())  # the least visible such start


def test_oracle_bounds_every_policy_and_passive_never_moves(ablation):
    df = pd.read_csv(ablation["results"])
    final = df[df["final"]]
    for split in ("train", "hard"):
        s = final[final["split"] == split].set_index("method")
        assert (s.drop(index="oracle")["return"] <= s.loc["oracle", "return"] + 1e-9).all()
        assert s.loc["passive", "path_m"] == 0.0 and s.loc["passive", "steps"] == 1.0


def test_interrupted_run_was_finished_not_restarted(ablation):
    job = ablation["interrupted"]
    assert is_done(job)
    evals = [json.loads(x) for x in Path(job.out, "evals.jsonl").read_text().splitlines()]
    assert ablation["partial_epochs"] == 2  # one epoch x two splits before the interruption
    points = [e["episodes"] for e in evals if e["split"] == "train"]
    assert len(points) == 2 and points[0] < 200 <= points[1]
    assert any("2 runs, 0 finished already, 2 to run" in x for x in ablation["log"])


def test_report_and_trajectories(ablation):
    out = ablation["plan"].out
    report = (out / "report" / "report.md").read_text()
    for section in ("## Results at the final evaluation point", "## Generalisation gap", "## Learning curves",
                    "## Observation sequences", "## Claims checked", "| MAP |", "| IBE-MAP |", "| Class-knowing oracle (upper bound) |",
                    "| Visibility oracle |"):
        assert section in report
    assert "(Fig. 9: learning curves: not drawn" in report and "(Fig. 8: observation sequences: not drawn" in report
    meta = json.loads((out / "ablation.json").read_text())
    assert meta["status"] == "done" and set(meta["stages"]) >= {"classifier", "tables", "training"}
    traj = json.loads((out / "trajectories.json").read_text())
    methods = {t["method"] for t in traj}
    assert methods == {"map", "ibe_map", "random", "oracle"}
    starts = {t["start_view"] for t in traj}
    assert len(starts) == 1 and all(t["views"][0] == t["start_view"] for t in traj)
    oracle = next(t for t in traj if t["method"] == "oracle")
    assert oracle["recognized"] and len(oracle["views"]) > 1  # passive fails there, the oracle moves and succeeds


def test_rerun_skips_finished_runs_and_rewrites_identical_results(ablation, tiny, tmp_path, monkeypatch):
    """Rerun on a copy of the finished ablation, as `uevavd ablate` runs it: the runner asks for
    the report's figures unless told not to (they are drawn by test_report.py; the report is
    written here without them: its text is what a rerun rewrites from the same files)."""
    import shutil

    import uevavd.experiments.runner as runner

    out = tmp_path / "again"
    shutil.copytree(ablation["plan"].out, out)
    before = pd.read_csv(ablation["results"])
    done = sorted(out.glob("runs/*/*/*/*/done.json"))
    mtimes = {p: p.stat().st_mtime_ns for p in done}
    assert len(done) == 2
    # what a kill while writing results.csv or saving a figure leaves: the rerun removes it
    left = [out / ".results.csv.k1ll3d.tmp", out / "report" / ".fig9_curves.pdf.k1ll3d.tmp.pdf"]
    for p in left:
        p.write_bytes(b"%PDF-1.4 half")
    asked, real = [], runner.write_report
    monkeypatch.setattr(runner, "write_report", lambda d, *, figures: asked.append(figures) or real(d, figures=False))
    lines: list[str] = []
    results = run_ablation(make_plan(preset=str(tiny["preset"]), out=out, data=tiny["world"], workers=1),
                           log=lines.append)
    assert asked == [True]
    assert any("2 runs, 2 finished already, 0 to run" in x for x in lines)
    assert any("reusing classifier" in x for x in lines)
    assert {p: p.stat().st_mtime_ns for p in done} == mtimes
    pd.testing.assert_frame_equal(pd.read_csv(results), before)
    assert not [p for p in left if p.exists()]


def test_a_finished_ablation_grows_to_more_seeds_in_place(ablation, tiny, tmp_path):
    import shutil

    out = tmp_path / "grown"
    shutil.copytree(ablation["plan"].out, out)
    before = pd.read_csv(ablation["results"])
    done = sorted(out.glob("runs/*/*/*/*/done.json"))
    mtimes = {p: p.stat().st_mtime_ns for p in done}
    lines: list[str] = []
    plan = make_plan(preset=str(tiny["preset"]), out=out, data=tiny["world"], workers=1, seeds=2, figures=False)
    after = pd.read_csv(run_ablation(plan, log=lines.append))
    assert any("4 runs, 2 finished already, 2 to run" in x for x in lines)
    assert {p: p.stat().st_mtime_ns for p in done} == mtimes  # the finished runs kept, not retrained
    learned = before["method"].isin(["map", "ibe_map"])
    assert learned.sum() > 0 and set(before.loc[learned, "seed"]) == {0}
    assert sorted(after.loc[after["method"].isin(["map", "ibe_map"]), "seed"].unique()) == [0, 1]
    kept = after[after["seed"].eq(0) & after["method"].isin(["map", "ibe_map"])].reset_index(drop=True)
    pd.testing.assert_frame_equal(kept[before.columns], before[learned].reset_index(drop=True),
                                  check_dtype=False)


def test_a_second_ablation_into_an_out_folder_another_is_writing_is_refused(tiny, tmp_path):
    """Two ablations with one --out would interleave results.csv and the report, and one could
    remove the other's temporary files: the second is refused at once, naming the lock."""
    from uevavd.atomic import folder_lock

    out = tmp_path / "busy"
    with folder_lock(out, RuntimeError), pytest.raises(AblationError, match=r"being written by another ablation.*\.busy\.lock"):
        run_ablation(make_plan(preset=str(tiny["preset"]), out=out, data=tiny["world"], workers=1))
    assert not out.exists()  # nothing written


def test_other_configuration_in_the_same_directory_is_refused(ablation, tiny):
    with pytest.raises(AblationError, match="another configuration"):
        run_ablation(_plan(tiny, "out", episodes=500), log=lambda *_: None)


def test_sweep_adds_settings_with_their_reward_constants(tiny):
    plan = _plan(tiny, "sweep", sweeps=parse_sweeps(["thre=0.2,0.6", "C=0"]), sweep_methods=["ibe_map"])
    names = dict(plan.settings("ibe_map"))
    assert list(names) == ["default", "thre=0.6", "C=0"]  # thre=0.2 is the default, run once
    assert names["thre=0.6"] == {"thre": 0.6, "C": 0.02} and names["C=0"] == {"thre": 0.2, "C": 0.0}
    assert [n for n, _ in plan.settings("map")] == ["default"]


@pytest.mark.parametrize(
    "kwargs, message",
    [
        ({"methods": ["map", "mapp"]}, r"unknown method 'mapp': known methods are \["),
        ({"seeds": 0}, r"--seeds 0: expected an integer in 1\.\.1000"),
        ({"seeds": 10**9}, r"--seeds 1000000000: expected an integer in 1\.\.1000"),  # was the kernel's kill
        ({"recognizers": 0}, r"--recognizers 0: expected an integer in 1\.\.100"),
        ({"sweep_methods": ["memo_map"]}, "not among --methods"),
        ({"backend": "slurm"}, "expected 'local' or 'ray'"),
        ({"device": "gpu"}, "--device: device 'gpu': expected 'auto', 'cpu', 'cuda'"),
        pytest.param({"device": "cuda"}, "--device: .*no CUDA device is available",
                     marks=pytest.mark.skipif(torch.cuda.is_available(), reason="a CUDA device is there")),
    ],
)
def test_bad_arguments_are_refused(tiny, kwargs, message):
    with pytest.raises(AblationError, match=message):
        _plan(tiny, "bad", **kwargs)


def test_a_sweep_over_any_dotted_key_runs_and_gets_its_column(ablation, tiny, tmp_path):
    """env.xi2 (the step penalty) swept for IBE-MAP beside the finished ablation: one run
    more, its settings.json and the baselines under that setting use xi2 = 0.3, and the
    results gain an env.xi2 column holding each row's resolved value."""
    import shutil

    out = tmp_path / "swept"
    shutil.copytree(ablation["plan"].out, out)
    plan = make_plan(preset=str(tiny["preset"]), out=out, data=tiny["world"], workers=1,
                     sweeps=parse_sweeps(["env.xi2=0.1,0.3"]), sweep_methods=["ibe_map"], figures=False)
    assert [n for n, _ in plan.settings("ibe_map")] == ["default", "env.xi2=0.3"]  # 0.1 is the default
    lines: list[str] = []
    df = pd.read_csv(run_ablation(plan, log=lines.append))
    assert any("3 runs, 2 finished already, 1 to run" in x for x in lines)
    assert list(df.columns) == [*RESULT_COLUMNS[:6], "env.xi2", *RESULT_COLUMNS[6:]]
    assert set(df.loc[df["setting"] == "default", "env.xi2"]) == {0.1}
    assert set(df.loc[df["setting"] == "env.xi2=0.3", "env.xi2"]) == {0.3}
    run = out / "runs" / "ibe_map" / "env.xi2=0.3" / "rec0" / "seed0"
    assert json.loads((run / "settings.json").read_text())["env"]["xi2"] == 0.3
    final = df[df["final"] & (df["split"] == "hard")].set_index(["method", "setting"])
    # passive stops at once (no step penalty); random flies, so a larger penalty lowers its return
    assert final.loc[("passive", "env.xi2=0.3"), "return"] == final.loc[("passive", "default"), "return"]
    assert final.loc[("random", "env.xi2=0.3"), "return"] < final.loc[("random", "default"), "return"]


def test_bad_presets_and_sweeps_are_refused(tmp_path):
    with pytest.raises(AblationError, match=r"unknown preset 'quik'.*quick"):
        make_plan(preset="quik", out=tmp_path / "a")
    with pytest.raises(AblationError, match=r"--sweep 'gamma'"):
        parse_sweeps(["gamma"])
    for key, message in (("gamma", "expected thre, C or a dotted key"), ("perception.gray_seed", r"perception.gray_seed = 'abc': expected int"),
                         ("stat.hidden", "did you mean 'state'"), ("thr", "did you mean 'thre'"),
                         ("env.xi2", r"--sweep env.xi2='abc' for method 'map'.*wrong type")):
        with pytest.raises(AblationError, match=message):
            make_plan(preset="quick", out=tmp_path / "s", methods=["map"], sweep_methods=["map"],
                      sweeps=parse_sweeps([f"{key}=abc"]))
    for kw, message in (({"episodes": 0}, r"with --episodes 0 for method 'map': .*train.episodes = 0"),
                        ({"sweeps": {"train.lr": [float("inf")]}, "sweep_methods": ["map"]},
                         r"--sweep train.lr=inf for method 'map'")):
        with pytest.raises(AblationError, match=message):  # ranges, before anything is written
            make_plan(preset="quick", out=tmp_path / "e", methods=["map"], **kw)
    assert not (tmp_path / "e").exists()
    bad = tmp_path / "bad.toml"
    bad.write_text('name = "bad"\n[world]\nseed = 0\nsize = 16\nper_block = { train = 1 }\n'
                   '[overrides]\n"train.episode" = 10\n')
    with pytest.raises(AblationError, match="episodes"):  # the close match is suggested
        make_plan(preset=str(bad), out=tmp_path / "b", methods=["map"])
    bad.write_text('name = "bad"\n[classifier]\nepoch = 2\n')
    with pytest.raises(AblationError, match=r"\[classifier\].*epochs"):
        make_plan(preset=str(bad), out=tmp_path / "c", methods=["map"], data=tmp_path)


def test_non_empty_foreign_directory_is_refused(tiny, tmp_path):
    (tmp_path / "notes.txt").write_text("mine")
    plan = make_plan(preset=str(tiny["preset"]), out=tmp_path, data=tiny["world"])
    with pytest.raises(AblationError, match="holds no ablation.json"):
        run_ablation(plan, log=lambda *_: None)
    assert (tmp_path / "notes.txt").read_text() == "mine"


@pytest.mark.parametrize("damage", ["truncated", "list", "edited"])
def test_a_damaged_ablation_json_is_one_line_naming_it_for_ablate_and_report(ablation, tiny, tmp_path, capsys,
                                                                             monkeypatch, damage):
    """A truncated ablation.json was a JSON error naming no file; a list-valued one an
    AttributeError traceback, in ablate's rerun and in report."""
    import shutil

    from uevavd.cli import main

    monkeypatch.delenv("UEVAVD_DEBUG", raising=False)
    out = tmp_path / "abl"
    shutil.copytree(ablation["plan"].out, out, ignore=shutil.ignore_patterns("runs"))
    meta = out / "ablation.json"
    text = meta.read_text()
    meta.write_text({"truncated": text[: len(text) // 2], "list": "[1, 2]",
                     "edited": text.replace('"seeds": 1', '"seeds": 2')}[damage])
    for argv in (["ablate", "--preset", str(tiny["preset"]), "--data", str(tiny["world"]), "--out", str(out)],
                 ["report", str(out)]):
        assert main(argv) == 2
        err = capsys.readouterr().err.strip().splitlines()[-1]
        assert f"{meta}: " in err and "Traceback" not in err, err


def test_an_ablation_json_whose_digest_was_removed_is_refused(ablation, tmp_path, capsys, monkeypatch):
    """ablation.json without its sha256 (and its mark) and with an edit: report printed "0 runs per
    method", exit 0. Beside sealed runs it must carry its digest."""
    import shutil

    from uevavd.cli import main

    monkeypatch.delenv("UEVAVD_DEBUG", raising=False)
    out = tmp_path / "abl"
    shutil.copytree(ablation["plan"].out, out)
    meta = json.loads((out / "ablation.json").read_text())
    meta = {k: v for k, v in meta.items() if k not in ("sha256", "sealed")}
    meta["seeds"] = []
    (out / "ablation.json").write_text(json.dumps(meta))
    assert main(["report", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert "ablation.json: damaged or edited (no sha256 digest" in err


def test_an_ablation_killed_in_its_first_write_reruns(tiny, tmp_path):
    """Killed while writing ablation.json for the first time, an ablation left only its temporary
    file, and the rerun called the folder someone else's."""
    out = tmp_path / "abl"
    out.mkdir()
    (out / ".ablation.json.k1ll3d.tmp").write_text('{"perception": ')
    plan = make_plan(preset=str(tiny["preset"]), out=out, data=tiny["world"])
    from uevavd.experiments.runner import check_out_dir

    check_out_dir(plan)  # not refused
    (out / "notes.txt").write_text("mine")
    with pytest.raises(AblationError, match="holds no ablation.json"):
        check_out_dir(plan)


def test_ray_backend_gives_the_local_results(ablation, tiny, local_ray):
    """Same jobs as Ray tasks on a local 1-CPU instance: identical evaluations."""
    import dataclasses

    from uevavd.experiments.backends import run_jobs

    local = [j for j in ablation["jobs"] if j.method == "map"]
    moved = [dataclasses.replace(j, out=str(tiny["root"] / "ray" / Path(j.out).name)) for j in local]
    run_jobs(moved, backend="ray", workers=1, log=lambda *_: None)
    assert local_ray.is_initialized()  # the backend used the running instance and left it running
    for a, b in zip(local, moved, strict=True):
        ea = [json.loads(x) for x in Path(a.out, "evals.jsonl").read_text().splitlines()]
        eb = [json.loads(x) for x in Path(b.out, "evals.jsonl").read_text().splitlines()]
        keys = ("episodes", "split", "mean_return", "accuracy", "path_m", "stop_rate")
        assert [[e[k] for k in keys] for e in ea] == [[e[k] for k in keys] for e in eb]
        assert is_done(b) and not math.isnan(eb[-1]["mean_return"])


def test_full_disk_surfaces_and_keeps_earlier_results(ablation, tiny, monkeypatch):
    """The disk fills while results.csv is rewritten: the error reaches the caller, the
    previous results.csv is intact and no temp file is left behind."""
    import errno
    import os

    results = ablation["results"]
    before = results.read_bytes()
    real_fsync = os.fsync

    def fsync(fd):
        if ".results.csv." in os.readlink(f"/proc/self/fd/{fd}"):
            raise OSError(errno.ENOSPC, "No space left on device")
        return real_fsync(fd)

    monkeypatch.setattr(os, "fsync", fsync)
    with pytest.raises(OSError, match="No space left"):
        run_ablation(_plan(tiny, "out"), log=lambda *_: None)
    assert results.read_bytes() == before
    assert not list(results.parent.glob(".results.csv.*"))


def test_unknown_preset_keys_are_refused(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text('name = "bad"\n[ablation]\nseed = 3\n')
    with pytest.raises(AblationError, match=r"\[ablation\]: unknown key\(s\) \['seed'\].*'seeds'"):
        make_plan(preset=str(bad), out=tmp_path / "a", data=tmp_path)
    bad.write_text('name = "bad"\n[worlds]\nsize = 3\n')
    with pytest.raises(AblationError, match=r"unknown section\(s\) \['worlds'\]"):
        make_plan(preset=str(bad), out=tmp_path / "a", data=tmp_path)


def test_per_context_rows_and_the_recognizer_audit(ablation):
    """contexts.csv holds one row per (policy, run, split, context) of the final evaluations,
    whose means over contexts are the results' final rows; recognizer_audit.json holds the
    clear-view accuracy per split and context."""
    out = ablation["results"].parent
    ctx = pd.read_csv(out / "contexts.csv")
    res = pd.read_csv(ablation["results"])
    final = res[res["final"] & (res["method"] == "map") & (res["split"] == "hard")]
    rows = ctx[(ctx["method"] == "map") & (ctx["split"] == "hard")]
    assert sorted(rows["context"]) == [26, 56]
    assert rows["return"].mean() == pytest.approx(float(final["return"].iloc[0]))
    assert {"visibility_oracle", "passive", "oracle"} <= set(ctx["method"])
    audit = json.loads((out / "recognizer_audit.json").read_text())
    hard = audit["0"]["splits"]["hard"]
    assert [c["context"] for c in hard["contexts"]] == [26, 56] and 0 <= hard["accuracy"] <= 1
    assert audit["0"]["classifier"]["arch"] == "resnet18"
    report = (out / "report" / "report.md").read_text()
    assert "## Recognizer audit" in report and report.index("## Recognizer audit") < report.index("## Results")


def test_two_recognizers_give_their_own_classifiers_tables_and_runs(tiny):
    """Recognizer seeds train separate classifiers with separate tables; a job per
    (method, setting, recognizer, seed)."""
    plan = _plan(tiny, "two-rec", recognizers=2)
    data = stage_world(plan, print)
    classifiers = stage_classifier(plan, data, print)
    assert sorted(classifiers) == [0, 1] and classifiers[0] != classifiers[1]
    tables = stage_tables(plan, data, classifiers, print)
    assert tables[0]["map"] != tables[1]["map"]
    jobs = plan_jobs(plan, tables)
    assert sorted({(j.method, j.recognizer) for j in jobs}) == [("ibe_map", 0), ("ibe_map", 1), ("map", 0), ("map", 1)]
    assert len({j.out for j in jobs}) == len(jobs)


def test_a_recognizer_another_process_is_making_is_waited_for_not_trained_again(tiny, tmp_path, monkeypatch):
    """Two ablations on one cache both trained the same recognizer at once (the tables had
    their lock, the recognizers none): the second now waits on the recognizer's lock, then
    reuses the first's file."""
    import subprocess
    import sys

    import uevavd.experiments.stages as stages
    from uevavd.data.reader import read_dataset
    from uevavd.perception.classifier import classifier_cache_path, data_hash, train_records
    from uevavd.perception.training.classifier import ClassifierRecipe

    monkeypatch.setenv("UEVAVD_CACHE", str(tmp_path / "cache"))
    plan = _plan(tiny, "waits")
    path = classifier_cache_path(data_hash(train_records(read_dataset(tiny["world"]))),
                                 ClassifierRecipe.from_preset(plan.preset, seed=0))
    path.parent.mkdir(parents=True)
    holder = ("import sys, time; from filelock import FileLock; lock = FileLock(sys.argv[1]); lock.acquire(); "
              "print('held', flush=True); time.sleep(1.0); open(sys.argv[2], 'wb').write(b'made by the other'); "
              "lock.release()")
    other = subprocess.Popen([sys.executable, "-c", holder, str(path.parent / f".{path.name}.lock"), str(path)],
                             stdout=subprocess.PIPE, text=True)
    try:
        assert other.stdout.readline() == "held\n"
        monkeypatch.setattr(stages, "train_classifier", lambda *a, **k: pytest.fail("trained it again"))
        lines: list[str] = []
        assert stages.stage_classifier(plan, tiny["world"], lines.append) == {0: path}
    finally:
        other.wait(timeout=60)
    assert "another process is making it" in lines[0] and lines[1] == f"  reusing classifier {path}"
    assert path.read_bytes() == b"made by the other"


def test_threads_follow_the_workers_asked_for_not_the_runs_left(monkeypatch):
    """For a method that sets ``train.threads = 0``, a resumed ablation with one run left gives
    it the thread count an uninterrupted one gave it (cores // workers), so its weights are
    the same (it used to get every core)."""
    import uevavd.experiments.backends as backends

    monkeypatch.setattr(backends, "usable_cores", lambda: 4)
    seen = []
    monkeypatch.setattr(backends, "run_local", lambda jobs, workers, log: seen.extend(jobs) or [])
    from uevavd.experiments.jobs import Job

    job = Job("map", "default", 0, "spec.toml", "table", "out")
    backends.run_jobs([job], workers=2)
    assert seen[0].threads == 2


def test_a_run_in_the_callers_process_leaves_its_torch_thread_count(monkeypatch):
    """With one local worker the runs train in the caller's process: each on its job's thread
    count, and the caller's count is back after it (the count stayed at the runs', so an
    ablation called from Python left every later torch call of the process on it)."""
    import uevavd.experiments.jobs as jobs

    seen = []
    monkeypatch.setattr(jobs, "load_method", lambda path: None)
    monkeypatch.setattr(jobs, "train", lambda *a, **k: seen.append(torch.get_num_threads()))
    monkeypatch.setattr(jobs, "final_eval", lambda job: seen.append(torch.get_num_threads()))
    before = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        jobs.run_job(jobs.Job("map", "default", 0, "spec.toml", "table", "out", threads=2))
        assert seen == [2, 2] and torch.get_num_threads() == 1
    finally:
        torch.set_num_threads(before)


def test_a_dead_worker_names_its_run_in_one_line(capsys, monkeypatch):
    """A killed ablation worker surfaced as BrokenProcessPool naming no run."""
    from concurrent.futures import Future
    from concurrent.futures.process import BrokenProcessPool

    from uevavd.cli import os_fault
    from uevavd.experiments.backends import job_result
    from uevavd.experiments.jobs import Job

    job = Job("ibe_map", "thre=0.4", 3, "spec.toml", "table", "/runs/ibe_map/thre=0.4/rec1/seed3", recognizer=1)
    fut = Future()
    fut.set_exception(BrokenProcessPool("A process in the process pool was terminated abruptly"))
    with pytest.raises(ChildProcessError, match=r"run ibe_map/thre=0.4/rec1/seed3 died.*rerun the same command") as e:
        job_result(fut, job)
    assert os_fault(e.value)  # the CLI prints it in one line, exit 2
    bad = Future()
    bad.set_exception(ValueError("table mismatch"))
    with pytest.raises(ValueError) as e2:
        job_result(bad, job)
    assert any("ibe_map/thre=0.4/rec1/seed3" in n for n in e2.value.__notes__)


def test_sb3_reference_rows_are_added_to_a_finished_ablation_without_retraining(ablation, tiny, tmp_path):
    pytest.importorskip("stable_baselines3")
    import shutil

    from uevavd.experiments.report_data import learned

    out = tmp_path / "with_sb3"
    shutil.copytree(ablation["plan"].out, out)
    plan = make_plan(preset=str(tiny["preset"]), out=out, data=tiny["world"], workers=1, sb3="dqn", figures=False)
    lines: list[str] = []
    results = run_ablation(plan, log=lines.append)
    assert any("2 runs, 2 finished already, 0 to run" in x for x in lines)  # nothing retrained
    df = pd.read_csv(results)
    ref = df[df["method"] == "sb3_dqn"]
    assert sorted(ref["split"]) == ["hard", "train"] and (ref["episodes"] == -1).all() and ref["final"].all()
    assert ref["return"].between(-1, 1).all()
    run = out / "runs" / "sb3_dqn" / "default" / "rec0" / "seed0"
    done = json.loads((out / "runs" / "map" / "default" / "rec0" / "seed0" / "done.json").read_text())
    assert json.loads((run / "final_eval.json").read_text())["env_steps"] == done["env_steps"]  # same env steps
    assert learned(df["method"].unique()) == ["map", "ibe_map"]  # a reference row, never a claimed method
    assert "SB3 DQN (reference)" in (out / "report" / "report.md").read_text()
    mtime = (run / "final_eval.json").stat().st_mtime_ns
    run_ablation(make_plan(preset=str(tiny["preset"]), out=out, data=tiny["world"], workers=1, sb3="dqn",
                           figures=False), log=lambda *_: None)
    assert (run / "final_eval.json").stat().st_mtime_ns == mtime  # cached: not trained again
    with pytest.raises(AblationError, match="--sb3 'a2c'"):
        make_plan(preset=str(tiny["preset"]), out=out, data=tiny["world"], sb3="a2c")


class _FirstRangeUp:
    """A plugin's baseline: one move of the first range in action type 0, then stop."""

    needs_features = False

    def reset(self, n):
        pass

    def act(self, obs):
        import torch

        n = obs["view"].shape[0]
        a_type = torch.where(obs["t"] == 0, torch.zeros(n, dtype=torch.int64), torch.full((n,), 6))
        return a_type, torch.zeros(n, dtype=torch.int64)


def build_first_range_up(*, table, config, seed=0):
    return _FirstRangeUp()


def test_a_plugin_baseline_joins_every_evaluation_and_is_never_counted_as_learned(ablation, tiny, tmp_path):
    import shutil
    import types

    from uevavd.env.baselines import reference_policies
    from uevavd.experiments.report_data import learned
    from uevavd.plugins import hookimpl
    from uevavd.plugins.manager import manager

    @hookimpl
    def register_baselines(registry):
        registry.add("first_range_up", f"{__name__}:build_first_range_up", summary="one move up, then stop",
                     label="One move up")

    manager.register_plugin(types.SimpleNamespace(register_baselines=register_baselines), name="baseline-test")
    try:
        out = tmp_path / "with_plugin_baseline"
        shutil.copytree(ablation["plan"].out, out)
        results = run_ablation(make_plan(preset=str(tiny["preset"]), out=out, data=tiny["world"], workers=1,
                                         figures=False), log=lambda *_: None)
        df = pd.read_csv(results)
        rows = df[df["method"] == "first_range_up"]
        assert sorted(rows["split"]) == ["hard", "train"] and (rows["episodes"] == -1).all()
        assert (rows["steps"] == 2.0).all()  # it really flew once and stopped
        assert learned(df["method"].unique()) == ["map", "ibe_map"]
        assert "One move up" in (out / "report" / "report.md").read_text()  # its registered label
        from uevavd.api import load_run

        run = load_run(ablation["plan"].out / "runs" / "map" / "default" / "rec0" / "seed0")
        assert list(reference_policies(run.table(), run.env_config)) == [
            "random", "passive", "box_gate", "pose_seek", "departure_ceiling", "departure_ceiling2",
            "visibility_oracle", "oracle", "first_range_up"]
        assert list(run.evaluate("hard").index) == ["map", "random", "passive", "box_gate", "pose_seek",
                                                    "departure_ceiling", "departure_ceiling2", "visibility_oracle",
                                                    "oracle", "first_range_up"]
        report = (out / "report" / "report.md").read_text()
    finally:
        manager.unregister_plugin("baseline-test")
    # the plugin uninstalled, the report reads the roles the ablation recorded: the same report,
    # first_range_up still a reference and never a learned method whose claims are judged
    from uevavd.experiments.report import write_report

    roles = json.loads((out / "ablation.json").read_text())["roles"]
    assert "first_range_up" in roles["baselines"] and roles["labels"]["first_range_up"] == "One move up"
    again = write_report(out, figures=False).read_text()
    assert "One move up" in again  # the recorded label, the plugin gone
    # every section after Setup (whose stage timings now include the first report's) is the same
    assert again.split("\n## ")[2:] == report.split("\n## ")[2:]
    setup = again.split("\n## ")[1]
    assert "references: " in setup and "One move up" in setup.split("references: ")[1].splitlines()[0]


def test_learned_methods_stay_together_in_the_report_order():
    """A plugin's learned method was sorted after the oracles, and every plugin baseline was
    drawn in the same dark gray; learned methods now come together, other baselines after
    them, the oracles last, each baseline in its own colour."""
    from uevavd.experiments.figures import baseline_colour
    from uevavd.experiments.report_data import order_methods, recorded_roles

    meta = {"roles": {"baselines": ["random", "passive", "visibility_oracle", "oracle", "my_ref", "a_ref"],
                      "deterministic": ["passive"], "labels": {"my_lstm": "LSTM-MAP"}}}
    with recorded_roles(meta):
        got = order_methods(["oracle", "my_ref", "my_lstm", "ibe_map", "a_ref", "random", "map", "visibility_oracle",
                             "passive"])
        from uevavd.experiments.report_data import label

        assert label("my_lstm") == "LSTM-MAP" and label("map") == "MAP" and label("a_ref") == "a_ref"
    assert got == ["random", "passive", "map", "ibe_map", "my_lstm", "a_ref", "my_ref", "visibility_oracle", "oracle"]
    others = ["a_ref", "my_ref"]
    assert baseline_colour("a_ref", others) != baseline_colour("my_ref", others)
    assert baseline_colour("passive", others) == "tab:brown"


def test_the_training_bar_counts_episodes_from_the_runs_files(ablation, tmp_path):
    """The bar over the runs' episodes reads each run's evals.jsonl: a run's last whole
    record (a half-written last line is skipped), 0 for a run not started, all its episodes
    for a finished one; the description counts the finished runs."""
    import dataclasses
    import shutil

    from uevavd.config import load_method
    from uevavd.experiments.backends import RunsProgress, episodes_trained

    job = ablation["jobs"][0]
    asked = load_method(job.spec_path).train_config().episodes
    recorded = json.loads(RunDir(job.out).evals.read_text().splitlines()[-1])["episodes"]
    assert episodes_trained(job) == recorded > 0
    partial = dataclasses.replace(job, out=str(tmp_path / "partial"), seed=101)  # (keys name runs)
    shutil.copytree(job.out, partial.out)
    with RunDir(partial.out).evals.open("a") as fh:
        fh.write('{"epoch": 99, "episodes": 999')  # a line being appended
    fresh = dataclasses.replace(job, out=str(tmp_path / "fresh"), seed=102)
    assert episodes_trained(partial) == recorded and episodes_trained(fresh) == 0
    with RunsProgress([partial, fresh], every=3600) as progress:
        assert (progress.bar.total, progress.bar.n) == (2 * asked, min(asked, recorded))
        assert progress.bar.initial == min(asked, recorded)  # the rate counts this call's episodes only
        progress.finished(fresh)
        assert progress.bar.n == min(asked, recorded) + asked and progress.bar.desc.startswith("runs 1/2")


def test_a_context_count_sweep_enlarges_the_world_and_keeps_the_presets_default(tmp_path):
    """``--sweep env.train_per_block=10,20`` on the quick preset: one world holding 20 training
    contexts per block and every test context, the default setting at the preset's 4, and the
    axis swept for every method (not only the sweep methods)."""
    plan = make_plan(preset="quick", out=tmp_path / "a", methods=["map", "ibe_map"],
                     sweeps=parse_sweeps(["env.train_per_block=4,10,20"]), sweep_methods=["ibe_map"])
    assert plan.preset["world"]["per_block"] == {"train": 20, "simple": 5, "hard": 5}
    assert plan.preset["overrides"]["env.train_per_block"] == 4
    for method in ("map", "ibe_map"):  # 4 is the default: run once
        assert [n for n, _ in plan.settings(method)] == ["default", "env.train_per_block=10",
                                                         "env.train_per_block=20"]
    from uevavd.presets import load_preset

    assert load_preset("quick")["world"]["per_block"]["train"] == 4  # the preset itself is untouched
    for bad in ("0", "21", "2.5"):
        with pytest.raises(AblationError, match=rf"env.train_per_block={bad}.*integers in 1..20"):
            make_plan(preset="quick", out=tmp_path / "b", methods=["map"],
                      sweeps=parse_sweeps([f"env.train_per_block={bad}"]))


def test_the_number_of_training_contexts_is_an_axis_of_the_ablation_and_its_report(tiny, tmp_path):
    """On data with two training contexts per block, sweeping ``env.train_per_block=1``: the
    runs and the baselines of that setting train and are evaluated on the first training
    context of each block, the hard contexts are the same for both settings, and the report
    gains the table and figure of the axis (the report's text written without figures; the
    axis's figure drawn by its section from this ablation's rows)."""
    from uevavd.experiments.report_contexts import contexts_section
    from uevavd.experiments.report_data import final_rows, load_results

    preset = tmp_path / "tiny.toml"
    preset.write_text(tiny_preset(ablation='methods = ["map"]\nseeds = 1\n'))
    world = tmp_path / "world"
    world.mkdir()
    for scene in tiny["world"].iterdir():  # contexts 1, 26, 31, 56 and train_605, linked (read only)
        (world / scene.name).symlink_to(scene, target_is_directory=True)
    write_tiny_world(world, contexts=(2, 32), train605=False)  # a second training context per block
    plan = make_plan(preset=str(preset), out=tmp_path / "out", data=world, workers=1,
                     sweeps=parse_sweeps(["env.train_per_block=1"]), figures=False)
    assert plan.preset["overrides"]["env.train_per_block"] == 0  # on --data the default is all of it
    df = pd.read_csv(run_ablation(plan, log=lambda *_: None))
    final = df[df["final"]].set_index(["method", "setting", "split"])
    for method in ("map", "passive", "oracle"):
        assert final.loc[(method, "default", "train"), "eval_contexts"] == 4
        assert final.loc[(method, "env.train_per_block=1", "train"), "eval_contexts"] == 2
        assert final.loc[(method, "env.train_per_block=1", "hard"), "eval_contexts"] == 2
    run = plan.out / "runs" / "map" / "env.train_per_block=1" / "rec0" / "seed0"
    assert json.loads((run / "settings.json").read_text())["env"]["train_per_block"] == 1
    ctx = pd.read_csv(plan.out / "contexts.csv")
    trained = ctx[(ctx["method"] == "map") & (ctx["split"] == "train")].groupby("setting")["context"]
    assert sorted(trained.unique()["env.train_per_block=1"]) == [1, 31]
    report = (plan.out / "report" / "report.md").read_text()
    assert "## Test return against the number of training contexts" in report
    assert "| MAP | 2 | 1 |" in report and "| MAP | 4 | 1 |" in report
    assert "(Test return against the number of training contexts: not drawn" in report
    drawn = contexts_section(final_rows(load_results(plan.out / "results.csv")), tmp_path, figures=True)
    assert "![Test return against the number of training contexts](fig_contexts.png)" in drawn
    assert (tmp_path / "fig_contexts.png").stat().st_size > 10_000


def test_a_sweep_that_would_run_on_no_method_or_outside_its_range_is_refused(tmp_path):
    """--sweep thre=0.4 with --methods map on the quick preset (whose sweep method is ibe_map)
    used to be dropped without a word; thre=nan and C=-1 were not checked either."""
    with pytest.raises(AblationError, match=r"--sweep thre would run on no method.*--sweep-methods"):
        make_plan(preset="quick", out=tmp_path / "a", methods=["map"], sweeps=parse_sweeps(["thre=0.4"]))
    plan = make_plan(preset="quick", out=tmp_path / "b", methods=["map"], sweeps=parse_sweeps(["thre=0.4"]),
                     sweep_methods=["map"])
    assert [n for n, _ in plan.settings("map")] == ["default", "thre=0.4"]
    for item, needle in (("thre=nan", r"--sweep thre=nan: .*thre"), ("C=-1", r"--sweep C=-1.0: .*C")):
        with pytest.raises(AblationError, match=needle):
            make_plan(preset="quick", out=tmp_path / "c", sweeps=parse_sweeps([item]))


def test_data_without_a_split_the_runs_are_evaluated_on_is_refused_before_any_work(tiny, tmp_path, capsys,
                                                                                   monkeypatch):
    """``ablate --data`` on a root without simple contexts, with a preset evaluating on them,
    failed only after the recognizer and the tables were made; now the world stage refuses it."""
    from uevavd.cli import main

    preset = tmp_path / "simple.toml"
    preset.write_text(TINY_PRESET.replace('["train", "hard"]', '["train", "simple", "hard"]'))
    plan = make_plan(preset=str(preset), out=tmp_path / "a", data=tiny["world"], workers=1, methods=["map"])
    with pytest.raises(AblationError, match=r"holds no contexts of split\(s\) \['simple'\].*holds \['hard', 'train'\]"):
        stage_world(plan, print)
    monkeypatch.delenv("UEVAVD_DEBUG", raising=False)
    capsys.readouterr()
    assert main(["ablate", "--preset", str(preset), "--data", str(tiny["world"]), "--methods", "map",
                 "--out", str(tmp_path / "b"), "--workers", "1"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "['simple']" in err, err
    assert not list((tmp_path / "b").glob("runs/*")) and not (tmp_path / "b" / "specs").exists()
    stage_world(_plan(tiny, "ok", methods=["map"]), print)  # train and hard only: accepted


def test_a_truncated_evals_jsonl_is_one_line_naming_it(ablation, tmp_path, capsys, monkeypatch):
    """A truncated `evals.jsonl` in a finished run made the rerun of `ablate` end in a JSON
    error naming no file."""
    import dataclasses
    import shutil

    from uevavd.experiments.results import run_rows

    job = ablation["jobs"][0]
    copy = tmp_path / "run"
    shutil.copytree(job.out, copy)
    evals = copy / "evals.jsonl"
    evals.write_text(evals.read_text()[:-25])
    damaged = dataclasses.replace(job, out=str(copy))
    with pytest.raises(ValueError, match=r"evals.jsonl, line \d+: damaged .*train the run again"):
        run_rows(damaged, {})


def test_an_edited_settings_json_of_an_ablation_run_is_refused_not_folded_into_its_setting(ablation, tmp_path):
    """thre edited in a finished run's settings.json became the run's rows under "default" on
    the ablation's rerun (its final evaluation redone under the edited value)."""
    import dataclasses
    import shutil

    from uevavd.experiments.results import run_rows
    from uevavd.hashing import DamagedFileError

    job = next(j for j in ablation["jobs"] if j.method == "map")
    copy = tmp_path / "run"
    shutil.copytree(job.out, copy)
    settings = copy / "settings.json"
    settings.write_text(settings.read_text().replace('"thre": 0.2', '"thre": 0.3'))
    with pytest.raises(DamagedFileError, match="settings.json: edited or damaged"):
        run_rows(dataclasses.replace(job, out=str(copy)), {"thre": 0.2, "C": 0.02})


def test_an_edited_final_eval_or_baselines_cache_is_not_used(ablation, tmp_path):
    """Values edited in a run's final_eval.json or in baselines.json went straight into
    results.csv; both are sealed with the sha256 of their JSON now, and an edited one is
    evaluated again."""
    import dataclasses
    import shutil

    from uevavd.atomic import read_sealed_json
    from uevavd.experiments.results import final_eval

    job = ablation["jobs"][0]
    copy = tmp_path / "run"
    shutil.copytree(job.out, copy)
    moved = dataclasses.replace(job, out=str(copy))
    true = final_eval(moved)["splits"]["hard"]["mean_return"]
    path = RunDir(copy).final_eval
    edited = json.loads(path.read_text())
    edited["splits"]["hard"]["mean_return"] = 0.99
    path.write_text(json.dumps(edited))
    assert final_eval(moved)["splits"]["hard"]["mean_return"] == true  # evaluated again, not 0.99
    assert read_sealed_json(path) is not None  # and sealed again
    baselines = ablation["plan"].out / "baselines.json"
    sealed = read_sealed_json(baselines)
    assert sealed is not None and any("|passive|" in k for k in sealed)
    data = json.loads(baselines.read_text())
    key = next(k for k in data if "|passive|" in k)
    data[key]["mean_return"] = 0.99
    shutil.copy(baselines, tmp_path / "baselines.json")
    (tmp_path / "baselines.json").write_text(json.dumps(data))
    assert read_sealed_json(tmp_path / "baselines.json") is None  # the edit is seen
    # and the rows are evaluated again, said in the ablation's log (this was an AttributeError)
    from uevavd.experiments.results import baseline_rows

    plan = dataclasses.replace(ablation["plan"], out=tmp_path)
    tables = {0: Path(next(j for j in ablation["jobs"] if j.method == plan.methods[0]).table)}
    said: list[str] = []
    rows, _ = baseline_rows(plan, tables, ["hard"], said.append)
    passive = [r for r in rows if r["method"] == "passive"]
    assert passive and all(r["return"] != 0.99 for r in passive)
    assert any("baselines.json is damaged or was edited" in line for line in said)
    assert read_sealed_json(tmp_path / "baselines.json") is not None


def test_result_rows_state_the_reward_constants_the_run_recorded(ablation):
    """results.csv's thre and C come from the run's own settings.json, not from the plan's
    setting dict (two sources for one value): a row never states another value than its
    run trained and was evaluated under."""
    from uevavd.experiments.results import run_rows

    job = next(j for j in ablation["jobs"] if j.method == "map")
    recorded = json.loads((Path(job.out) / "settings.json").read_text())["env"]
    rows = run_rows(job, {"thre": 0.9, "C": 0.5})
    assert rows and {(r["thre"], r["C"]) for r in rows} == {(recorded["thre"], recorded["C"])}


def test_a_plan_resolves_each_method_spec_once(tiny, monkeypatch, tmp_path):
    """make_plan resolves (and so checks) each (method, setting) it runs once; the stages,
    the runs' spec files and the progress bar read those specs; a worker resolves its run's
    spec once more, from the file (4 resolutions of one spec before)."""
    import uevavd.experiments.jobs as jobs_module
    import uevavd.experiments.plan as plan_module

    calls = []
    real = plan_module.load_method
    counting = lambda *a, **k: calls.append(a[0]) or real(*a, **k)  # noqa: E731
    monkeypatch.setattr(plan_module, "load_method", counting)
    monkeypatch.setattr(jobs_module, "load_method", counting)
    plan = _plan(tiny, "specs-once", sweeps={"thre": [0.4], "train.lr": [0.01]})
    settings = {m: [name for name, _ in plan.settings(m)] for m in plan.methods}
    assert settings == {"map": ["default"], "ibe_map": ["default", "thre=0.4", "train.lr=0.01"]}
    assert sorted(calls) == ["ibe_map"] * 3 + ["map"]
    for _ in range(3):
        assert plan.spec("map") is plan.spec("map", dict(plan_module.DEFAULT_SETTING))
        plan.spec("ibe_map")
    fake_tables = {0: {m: tmp_path / "table" for m in plan.methods}}
    plan.out = tmp_path / "out"
    for _ in range(2):  # the second as a resumed ablation: the spec files are read, not resolved
        jobs = plan_jobs(plan, fake_tables)
    assert sorted(calls) == ["ibe_map"] * 3 + ["map"]
    assert {j.episodes for j in jobs} == {plan.spec("map").train_config().episodes}
    import pickle

    assert "_specs" not in pickle.loads(pickle.dumps(plan)).__dict__  # a worker gets the plan without them


def test_the_baselines_env_of_a_setting_that_sweeps_another_methods_head(tmp_path):
    """A swept head key of the second method only (ibe_map_ens's head.kappa) failed the
    evaluation stage after every run had trained: the baselines' env config resolved the
    setting on the first method, whose head has no such key."""
    from uevavd.experiments.plan import env_config

    plan = make_plan(preset="quick", out=tmp_path / "k", methods=["ibe_map", "ibe_map_ens"],
                     sweep_methods=["ibe_map_ens"], sweeps={"head.kappa": [0.0], "env.xi2": [0.2]})
    settings = dict(plan.all_settings())
    assert env_config(plan, settings["head.kappa=0"]) == env_config(plan, settings["default"])
    assert env_config(plan, settings["env.xi2=0.2"]).xi2 == 0.2


class _FloatActions:
    """A broken baseline: its actions are not integers."""

    needs_features = False

    def reset(self, n):
        pass

    def act(self, obs):
        n = len(obs["t"])
        return torch.full((n,), 0.5), torch.zeros(n)


def build_float_actions(*, table, config, seed=0):
    return _FloatActions()


def build_no_feature_dim(*, input_dim=8, state_dim=8):
    return torch.nn.Linear(input_dim, state_dim)


@pytest.mark.parametrize("broken", ["baseline", "state"])
def test_a_broken_plugin_component_is_refused_before_ablate_or_evaluate_write_anything(
        broken, ablation, tiny, tmp_path, capsys, monkeypatch):
    """A broken plugin baseline failed every evaluate, and ablate only after training every run,
    naming neither the baseline nor the plugin; ablate checked a method's components only after
    its world, recognizer and table stages and after writing ablation.json, specs/ and runs/."""
    import types

    from uevavd.cli import main
    from uevavd.env import baselines
    from uevavd.plugins import hookimpl
    from uevavd.plugins.manager import manager

    @hookimpl
    def register_baselines(registry):
        registry.add("floaty", f"{__name__}:build_float_actions", summary="float actions")

    @hookimpl
    def register_state_estimators(registry):
        registry.add("no_feature_dim", f"{__name__}:build_no_feature_dim", summary="takes no feature_dim")

    method = tmp_path / "broken_state.toml"
    method.write_text('_base_ = "map"\nname = "broken_state"\n[state]\nname = "no_feature_dim"\n')

    @hookimpl
    def register_methods(registry):
        registry.add("broken_state", str(method), summary="MAP over the broken state")

    hooks = {"baseline": {"register_baselines": register_baselines},
             "state": {"register_state_estimators": register_state_estimators,
                       "register_methods": register_methods}}[broken]
    monkeypatch.delenv("UEVAVD_DEBUG", raising=False)
    monkeypatch.setattr(baselines, "_CHECKED", set())
    manager.register_plugin(types.SimpleNamespace(**hooks), name="broken-test")
    try:
        out = tmp_path / "abl"
        argv = ["ablate", "--preset", str(tiny["preset"]), "--data", str(tiny["world"]), "--out", str(out),
                "--workers", "1"]
        if broken == "state":
            argv += ["--methods", "broken_state"]
        assert main(argv) == 2
        err = capsys.readouterr().err.strip().splitlines()[-1]
        assert ("'floaty'" if broken == "baseline" else "'no_feature_dim'") in err and "broken-test" in err, err
        assert not out.exists()
        if broken == "baseline":
            run = ablation["plan"].out / "runs" / "map" / "default" / "rec0" / "seed0"
            assert main(["evaluate", str(run), "--split", "hard", "--json", str(tmp_path / "e.json")]) == 2
            err = capsys.readouterr().err.strip().splitlines()[-1]
            assert "baseline 'floaty'" in err and "plugin 'broken-test'" in err and "Traceback" not in err, err
            assert not (tmp_path / "e.json").exists()
    finally:
        manager.unregister_plugin("broken-test")


def test_the_world_seed_draws_another_world_of_the_same_kind(tmp_path, capsys):
    from uevavd.presets import world_root

    one = make_plan(preset="quick", out=tmp_path / "a", methods=["map"])
    two = make_plan(preset="quick", out=tmp_path / "b", methods=["map"], world_seed=1)
    assert one.preset["world"]["seed"] == 0 and two.preset["world"]["seed"] == 1
    assert {k: v for k, v in two.preset["world"].items() if k != "seed"} == {
        k: v for k, v in one.preset["world"].items() if k != "seed"}
    assert world_root(one.preset) != world_root(two.preset)  # its own cached world
    with pytest.raises(AblationError, match="--world-seed -1: expected an integer in 0"):
        make_plan(preset="quick", out=tmp_path / "c", methods=["map"], world_seed=-1)
    with pytest.raises(AblationError, match="not with --data"):
        make_plan(preset="quick", out=tmp_path / "d", methods=["map"], world_seed=1, data=tmp_path)
    with pytest.raises(SystemExit) as exit_:
        main(["ablate", "--preset", "quick", "--world-seed", "x", "--out", str(tmp_path / "e")])
    assert exit_.value.code == 2 and "--world-seed" in capsys.readouterr().err
