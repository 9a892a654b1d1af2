"""Every file of a run that a reported number depends on carries a digest written with it and
checked where it is read: an edited value is refused in one line naming the file, never a
silently different result."""

from __future__ import annotations

import json
import shutil

import pytest

from uevavd.cli import main
from uevavd.config import load_method
from uevavd.hashing import DamagedFileError
from uevavd.policy.checkpoint import read_policy_file
from uevavd.policy.rundir import read_done, read_evals, read_settings
from uevavd.policy.trainer import train

from .conftest import small
from .test_cli import _one_line_error


@pytest.fixture(scope="module")
def run(table, tmp_path_factory):
    root = tmp_path_factory.mktemp("digests")
    spec = load_method("map", overrides={**small("map"), "train.episodes": 200})
    train(spec, table, out=root / "run", device="cpu", progress=False)
    table.save(root / "table")
    return root / "run"


def _copy(run, tmp_path):
    out = tmp_path / "run"
    shutil.copytree(run, out)
    return out


def test_an_edited_value_in_settings_json_is_refused_by_evaluate(run, tmp_path, capsys, monkeypatch):
    """thre 0.2 -> 0.3 in settings.json moved every row of `uevavd evaluate RUN`, exit 0."""
    monkeypatch.delenv("UEVAVD_DEBUG", raising=False)
    copy = _copy(run, tmp_path)
    text = (copy / "settings.json").read_text()
    assert '"thre": 0.2' in text
    (copy / "settings.json").write_text(text.replace('"thre": 0.2', '"thre": 0.3'))
    assert main(["evaluate", str(copy), "--split", "hard", "--json", str(tmp_path / "e.json")]) == 2
    _one_line_error(capsys, f"{copy / 'settings.json'}: edited or damaged since it was written")
    assert not (tmp_path / "e.json").exists()
    # and a resume of the run is refused the same way, not folded into another configuration
    with pytest.raises(DamagedFileError, match="settings.json: edited or damaged"):
        read_settings(copy)


@pytest.mark.parametrize("name, old, new", [
    ("evals.jsonl", '"epoch": 1', '"epoch": 7'),
    ("done.json", '"episodes": ', '"episodes": 1'),
])
def test_an_edited_digit_in_evals_or_done_is_refused_naming_the_file(run, tmp_path, name, old, new):
    copy = _copy(run, tmp_path)
    path = copy / name
    text = path.read_text()
    assert old in text
    path.write_text(text.replace(old, new, 1))
    read = read_evals if name == "evals.jsonl" else read_done
    with pytest.raises(DamagedFileError, match=rf"{name}(, line 1)?: edited or damaged"):
        read(copy)
    assert read(run)  # the intact run reads


def test_rows_of_an_earlier_version_without_digests_still_read(run, tmp_path):
    """Runs written before the files were sealed are read as they are."""
    copy = _copy(run, tmp_path)
    earlier = ("sha256", "sealed", "run")  # an earlier version wrote none of these
    for name in ("settings.json", "done.json"):
        obj = json.loads((copy / name).read_text())
        (copy / name).write_text(json.dumps({k: v for k, v in obj.items() if k not in earlier}))
    rows = [json.loads(line) for line in (copy / "evals.jsonl").read_text().splitlines()]
    (copy / "evals.jsonl").write_text("".join(json.dumps({k: v for k, v in r.items() if k not in earlier}) + "\n"
                                              for r in rows))
    assert read_settings(copy)["env"] == read_settings(run)["env"]
    assert read_evals(copy) == read_evals(run) and read_done(copy) == read_done(run)


@pytest.mark.parametrize("name", ["settings.json", "done.json", "evals.jsonl"])
def test_a_record_whose_digest_was_removed_is_refused(run, tmp_path, name):
    """Every reader took a file without its sha256 as one of an earlier version: deleting the key
    turned the check off. A record marked sealed, or beside sealed ones, must carry its digest."""
    from uevavd.policy.rundir import read_done, read_evals, read_settings

    read = {"settings.json": read_settings, "done.json": read_done, "evals.jsonl": read_evals}[name]
    for drop in (("sha256",), ("sha256", "sealed")):  # the digest; the digest and the mark
        copy = _copy(run, tmp_path / "-".join(drop))
        if name.endswith(".jsonl"):  # its first line
            lines = (copy / name).read_text().splitlines()
            lines[0] = json.dumps({k: v for k, v in json.loads(lines[0]).items() if k not in drop})
            (copy / name).write_text("\n".join(lines) + "\n")
        else:
            obj = json.loads((copy / name).read_text())
            (copy / name).write_text(json.dumps({k: v for k, v in obj.items() if k not in drop}))
        with pytest.raises(DamagedFileError, match=rf"{name}(, line 1)?: damaged or edited \(no sha256 digest"):
            read(copy)


@pytest.mark.parametrize("field, old, new", [
    ("method_toml", "thre = 0.2", "thre = 0.3"),
    ("settings", '"seed": 0', '"seed": 1'),
])
def test_an_edited_policy_file_header_is_refused(run, tmp_path, capsys, monkeypatch, field, old, new):
    """The header's method TOML and settings sat outside the weights' digest: an edited thre
    or kappa there changed the results of `uevavd evaluate FILE`."""
    from safetensors import safe_open
    from safetensors.torch import load_file, save_file

    monkeypatch.delenv("UEVAVD_DEBUG", raising=False)
    src = run / "policy.safetensors"
    with safe_open(str(src), framework="pt") as fh:
        meta = dict(fh.metadata())
    if field == "method_toml" and old not in meta[field]:
        meta[field] = meta[field].replace("[env]", "[env]\nthre = 0.2")
    assert old in meta[field]
    meta[field] = meta[field].replace(old, new, 1)
    edited = tmp_path / "policy.safetensors"
    save_file(load_file(str(src)), str(edited), metadata=meta)
    with pytest.raises(DamagedFileError, match="policy.safetensors: edited or damaged"):
        read_policy_file(edited)
    assert main(["evaluate", str(edited), "--table", str(run.parent / "table"), "--split", "hard"]) == 2
    _one_line_error(capsys, "policy.safetensors: edited or damaged")
    read_policy_file(src)


def test_an_edited_method_toml_of_a_run_is_refused(run, tmp_path, capsys, monkeypatch):
    """The network a run's policy is rebuilt with comes from its method.toml: an edited head
    or gate value there changed `uevavd evaluate RUN`; the spec hash in the sealed
    settings.json vouches for it now."""
    monkeypatch.delenv("UEVAVD_DEBUG", raising=False)
    copy = _copy(run, tmp_path)
    text = (copy / "method.toml").read_text()
    assert "hidden = 16" in text
    (copy / "method.toml").write_text(text.replace("hidden = 16", "hidden = 17"))
    assert main(["evaluate", str(copy), "--table", str(run.parent / "table"), "--split", "hard",
                 "--json", str(tmp_path / "e.json")]) == 2
    _one_line_error(capsys, f"{copy / 'method.toml'}: edited since the run wrote it")


def test_another_runs_records_copied_in_are_refused(table, tmp_path):
    """Two seeds' evals.jsonl swapped in an ablation moved 18 cells of results.csv, exit 0; one
    seed's done.json in the other relabelled its final rows: each record carries its run's mark."""
    import shutil

    from uevavd.hashing import DamagedFileError
    from uevavd.policy.rundir import read_done, read_evals

    spec = load_method("map", overrides={**small("map"), "train.episodes": 200})
    runs = [train(spec, table, out=tmp_path / f"seed{s}", seed=s, device="cpu", progress=False) for s in (0, 1)]
    assert read_evals(runs[0]) and "run" not in read_evals(runs[0])[0] and "run" not in read_done(runs[0])
    for name, read in (("evals.jsonl", read_evals), ("done.json", read_done)):
        shutil.copy(runs[1] / name, runs[0] / name)
        with pytest.raises(DamagedFileError, match=rf"seed0/{name}(, line 1)?: written by another run"):
            read(runs[0])


def test_an_unsealed_settings_json_with_another_reward_is_refused_by_the_checkpoint(table, tmp_path, capsys,
                                                                                     monkeypatch):
    """settings.json without its sha256 and with env.thre 0.3: evaluate took it (MAP 0.2669 -> 0.1697)
    though the checkpoint records thre 0.2; the checkpoint's env is compared now."""
    monkeypatch.delenv("UEVAVD_DEBUG", raising=False)
    spec = load_method("map", overrides={**small("map"), "train.episodes": 200})
    run = train(spec, table.save(tmp_path / "table"), out=tmp_path / "run", device="cpu", progress=False)
    assert main(["evaluate", str(run), "--split", "hard"]) == 0
    capsys.readouterr()
    earlier = ("sha256", "sealed", "run")  # every record stripped to look like an earlier version's
    for name in ("done.json", "settings.json"):
        obj = {k: v for k, v in json.loads((run / name).read_text()).items() if k not in earlier}
        if name == "settings.json":
            obj["env"]["thre"] = 0.3
        (run / name).write_text(json.dumps(obj))
    rows = [json.loads(line) for line in (run / "evals.jsonl").read_text().splitlines()]
    (run / "evals.jsonl").write_text("".join(json.dumps({k: v for k, v in r.items() if k not in earlier}) + "\n"
                                             for r in rows))
    assert main(["evaluate", str(run), "--split", "hard"]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "belongs to another configuration: env: checkpoint has" in err and "'thre': 0.2" in err


def test_a_policy_header_without_its_digests_is_refused(run, tmp_path):
    """A policy header with its sha256 and weights_hash removed took other weights."""
    from safetensors import safe_open
    from safetensors.torch import load_file, save_file

    src = run / "policy.safetensors"
    with safe_open(str(src), framework="pt") as fh:
        meta = dict(fh.metadata())
    assert meta["format"] == "uevavd-policy/2"
    weights = {k: v + 1.0 if v.is_floating_point() else v for k, v in load_file(str(src)).items()}
    for drop in (("sha256",), ("sha256", "sealed", "weights_hash")):  # this format's files always carry both
        edited = tmp_path / f"{len(drop)}.safetensors"
        save_file(weights, str(edited), metadata={k: v for k, v in meta.items() if k not in drop})
        with pytest.raises(DamagedFileError, match=r"\d.safetensors: damaged or edited .no sha256 digest"):
            read_policy_file(edited)


def test_a_first_format_policy_is_read_only_when_it_is_a_zoo_file(run, tmp_path, capsys, monkeypatch):
    """A policy rewritten as uevavd-policy/1 (no digest) with env.thre edited evaluated with exit 0
    (0.267 -> 0.170); an edited copy of the zoo's own format-1 file passed too. Format 1 is read
    for the files the zoo's manifests list, and refused with the way out otherwise."""
    from safetensors import safe_open
    from safetensors.torch import load_file, save_file

    from uevavd.policy.checkpoint import shipped_policy_digests
    from uevavd.presets import ZOO

    monkeypatch.delenv("UEVAVD_DEBUG", raising=False)
    src = run / "policy.safetensors"
    with safe_open(str(src), framework="pt") as fh:
        meta = dict(fh.metadata())
    settings = json.loads(meta["settings"])
    settings["env"]["thre"] = 0.1
    legacy = {"format": "uevavd-policy/1", "method_toml": meta["method_toml"], "settings": json.dumps(settings)}
    edited = tmp_path / "legacy.safetensors"
    save_file(load_file(str(src)), str(edited), metadata=legacy)
    with pytest.raises(Exception, match=r"legacy.safetensors: a uevavd-policy/1 file, whose header no digest protects"):
        read_policy_file(edited)
    assert main(["evaluate", str(edited), "--table", str(run.parent / "table"), "--split", "hard"]) == 2
    _one_line_error(capsys, "save the policy again from its run")
    shipped = ZOO / "pretrained" / "quick" / "map.safetensors"
    read_policy_file(shipped)  # the zoo's own file, byte for byte its manifest's
    assert len(shipped_policy_digests()) >= 4
    with safe_open(str(shipped), framework="pt") as fh:
        header = dict(fh.metadata())
    copy = tmp_path / "map.safetensors"
    save_file(load_file(str(shipped)), str(copy), metadata={**header, "method_toml": header["method_toml"] + "\n"})
    with pytest.raises(Exception, match="whose header no digest protects"):
        read_policy_file(copy)


@pytest.mark.parametrize("edit, message", [
    (lambda lines: [lines[0], *lines], r"evals.jsonl, line 2: epoch 1, split train where .* belongs \(lines deleted"),
    (lambda lines: lines[:1] + lines[2:], r"evals.jsonl, line 3: epoch 2, split hard where .* belongs \(lines deleted"),
    (lambda lines: [lines[1], lines[0], *lines[2:]], r"evals.jsonl, line 3: .* belongs \(lines deleted"),
    (lambda lines: lines[:-2], r"rows that are not the \d+ the finished run recorded in done.json"),
])
def test_a_runs_evals_are_bound_as_a_whole(table, tmp_path, edit, message):
    """Each line was sealed, the set was not: a duplicated line gave results.csv a row more, a
    deleted one a row less, a swapped pair reordered rows, and a finished run's last lines
    deleted left a short curve, without a word."""
    from uevavd.hashing import DamagedFileError
    from uevavd.policy.rundir import read_evals

    spec = load_method("map", overrides={**small("map"), "train.episodes": 300, "train.epoch_episodes": 100,
                                         "train.eval_splits": ["train", "hard"]})
    run = train(spec, table, out=tmp_path / "run", device="cpu", progress=False)
    lines = (run / "evals.jsonl").read_text().splitlines()
    assert len(read_evals(run)) == len(lines) == 6
    (run / "evals.jsonl").write_text("\n".join(edit(lines)) + "\n")
    with pytest.raises(DamagedFileError, match=message):
        read_evals(run)
