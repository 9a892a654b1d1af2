"""The model zoo: the shipped files match the world, the preset and the methods, and a
shipped policy reproduces its published numbers on a freshly generated context."""

from __future__ import annotations

import json
import re
import shutil

import pytest

from uevavd.presets import load_preset, world_contexts
from uevavd.pretrained import evaluate_pretrained
from uevavd.zoo import MANIFEST, PUBLISHED, Zoo, ZooError, scene_digest


def test_shipped_zoo_matches_the_world_generator_the_preset_and_the_methods():
    zoo = Zoo.load("quick")
    assert zoo.problems() == [], "the zoo is stale: rebuild it with `uevavd zoo build`"
    assert zoo.methods == ["ibe_map", "map", "memo_map"]
    for name in zoo.manifest["files"]:
        zoo.verified(name)  # every file hashes to its record
    preset = load_preset("quick")
    assert set(zoo.manifest["world"]["scenes"]) >= {f"{c:03d}" for c in world_contexts(preset)}
    for m in zoo.methods:
        assert set(zoo.manifest["policies"][m]["published"]) == {"train", "simple", "hard"}
    assert sum(r["bytes"] for r in zoo.manifest["files"].values()) < 25e6


def test_pretrained_policy_reproduces_its_published_numbers_on_a_fresh_context(tmp_path, monkeypatch):
    import uevavd

    monkeypatch.setenv("UEVAVD_CACHE", str(tmp_path / "cache"))
    zoo = Zoo.load("quick")
    frame = uevavd.evaluate_pretrained("map", "hard", contexts=[26], workers=1, progress=False, baselines=False)
    published, per_context = frame.attrs["published"], frame.attrs["per_context"]
    # the world was rendered here, byte for byte the one the zoo was trained and evaluated on
    scene = next((tmp_path / "cache" / "worlds").glob("world-*-26")) / "026" / "scene.json"
    assert scene_digest(scene) == zoo.manifest["world"]["scenes"]["026"]
    assert list(per_context["context"]) == [26]
    assert {k: float(frame.loc["map", k]) for k in PUBLISHED} == published


def test_an_altered_or_stale_zoo_is_refused_naming_the_file(tmp_path):
    root = tmp_path / "zoo"
    shutil.copytree(Zoo.load("quick").root, root)
    data = bytearray((root / "map.safetensors").read_bytes())
    data[-1] ^= 1
    (root / "map.safetensors").write_bytes(bytes(data))
    zoo = Zoo.load(root=root)
    with pytest.raises(ZooError, match=r"map.safetensors: sha256 .* does not match the manifest"):
        zoo.policy("map")
    with pytest.raises(ZooError, match="map.safetensors: sha256"):
        evaluate_pretrained("map", "hard", zoo=zoo, progress=False)
    zoo.recognizer()  # the other files are still fine
    with pytest.raises(ZooError, match=r"no pretrained 'sac' in the zoo: it ships \['ibe_map', 'map', 'memo_map'\]"):
        zoo.policy("sac")
    manifest = json.loads((root / MANIFEST).read_text())
    manifest["world"]["generator_version"] -= 1
    (root / MANIFEST).write_text(json.dumps(manifest))
    stale = Zoo.load(root=root)
    assert any("generator version" in p for p in stale.problems())
    with pytest.raises(ZooError, match="is stale .*generator version.*uevavd zoo build"):
        evaluate_pretrained("ibe_map", "hard", zoo=stale, progress=False)


def test_zoo_check_names_a_damaged_file(tmp_path, capsys):
    """`uevavd zoo check` printed that the shipped models match while a zoo file failed its
    sha256; it lists the file and exits 1 now."""
    from uevavd.cli import main

    root = tmp_path / "zoo"
    shutil.copytree(Zoo.load("quick").root, root)
    victim = root / "map.safetensors"
    data = bytearray(victim.read_bytes())
    data[-100] ^= 1
    victim.write_bytes(bytes(data))
    assert main(["zoo", "check", "--zoo", str(root)]) == 1
    out = capsys.readouterr().out
    assert "map.safetensors: sha256" in out and "does not match the manifest" in out and "match the world" not in out


def test_zoo_check_render_compares_the_world_rendered_here_with_the_records(tmp_path, capsys, monkeypatch):
    """`uevavd zoo check --render` tells a user whether this machine renders the zoo's world
    byte for byte (the world's bytes are numpy's arithmetic, which a CPU can change)."""
    from uevavd.cli import main

    monkeypatch.delenv("UEVAVD_DEBUG", raising=False)
    assert main(["zoo", "check", "--render", "026", "--workers", "1"]) == 0
    assert "1 of 1 scenes render here byte for byte as the zoo's records" in capsys.readouterr().out
    root = tmp_path / "zoo"
    shutil.copytree(Zoo.load("quick").root, root)
    manifest = json.loads((root / MANIFEST).read_text())
    manifest["world"]["scenes"]["026"] = "0" * 64  # as a machine that renders 026 otherwise would see it
    (root / MANIFEST).write_text(json.dumps(manifest))
    assert main(["zoo", "check", "--zoo", str(root), "--render", "026", "--workers", "1"]) == 1
    assert "1 of 1 scenes render otherwise here than the zoo's records: 026." in capsys.readouterr().out
    # several scenes, some of them otherwise: the count of each, and only those named (the two
    # renders above are the comparison itself; a third would take 4 s)
    asked = []
    with monkeypatch.context() as m:
        m.setattr(Zoo, "rendered_here", lambda self, scenes, **kw: asked.append(scenes) or {
            "001": True, "026": False, "031": True})
        assert main(["zoo", "check", "--zoo", str(root), "--render", "001,026,031", "--workers", "1"]) == 1
    assert asked == [["001", "026", "031"]]
    assert "1 of 3 scenes render otherwise here than the zoo's records: 026." in capsys.readouterr().out
    assert main(["zoo", "check", "--render", "999"]) == 2
    assert "scene(s) ['999'] are not in the zoo's records" in capsys.readouterr().err
    assert main(["zoo", "check", "--render", "026", "--workers", "0"]) == 2
    assert "--workers 0: expected at least 1" in capsys.readouterr().err


@pytest.mark.slow
def test_zoo_check_recognizer_trains_the_shipped_recognizer_here(tmp_path, capsys, monkeypatch):
    """`uevavd zoo check --recognizer` renders train_605 and trains the shipped recipe on this
    machine's CPU: the zoo's recognizer, bit for bit, on the fixed thread count (about 75 s).
    A zoo whose recognizer was trained on other train_605 bytes is named, not trained."""
    from uevavd.cli import main

    monkeypatch.delenv("UEVAVD_DEBUG", raising=False)
    assert main(["zoo", "check", "--recognizer", "--workers", "2"]) == 0
    assert "the recognizer trained here has the shipped recognizer's weights, bit for bit" in capsys.readouterr().out
    root = tmp_path / "zoo"
    shutil.copytree(Zoo.load("quick").root, root)
    manifest = json.loads((root / MANIFEST).read_text())
    manifest["recognizer"]["cache_name"] = "0" * 16 + manifest["recognizer"]["cache_name"][16:]
    (root / MANIFEST).write_text(json.dumps(manifest))
    assert main(["zoo", "check", "--zoo", str(root), "--recognizer", "--workers", "2"]) == 1
    assert "train_605 renders otherwise here than the zoo's recognizer was trained on" in capsys.readouterr().out


def test_a_manifest_naming_files_outside_the_zoo_or_without_sizes_is_refused(tmp_path, capsys, monkeypatch):
    """`zoo check` hashed /etc/hostname and said "match", Zoo.policy returned a path outside the
    zoo, and `zoo list` on a record without bytes was KeyError: 'bytes'."""
    from uevavd.cli import main

    monkeypatch.delenv("UEVAVD_DEBUG", raising=False)
    shipped = json.loads((Zoo.load("quick").root / MANIFEST).read_text())
    outside = tmp_path / "hostname"
    outside.write_text("host")
    cases = {
        "absolute": ({str(outside): {"sha256": "0" * 64, "bytes": 4}}, "lies outside the zoo folder"),
        "up": ({"../hostname": {"sha256": "0" * 64, "bytes": 4}}, "lies outside the zoo folder"),
        "no size": ({"map.safetensors": {"sha256": "0" * 64}}, "needs a sha256 .64 hex digits. and its size"),
    }
    for case, (extra, needle) in cases.items():
        root = tmp_path / case.replace(" ", "_")
        shutil.copytree(Zoo.load("quick").root, root)
        manifest = json.loads(json.dumps(shipped))
        manifest["files"].update(extra)
        if case == "absolute":
            manifest["policies"]["map"]["file"] = str(outside)
        (root / MANIFEST).write_text(json.dumps(manifest))
        with pytest.raises(ZooError, match=needle):
            Zoo.load(root=root)
        for command in ("check", "list"):
            assert main(["zoo", command, "--zoo", str(root)]) == 2, (case, command)
            err = capsys.readouterr().err.strip()
            assert "\n" not in err and re.search(needle, err), (case, command, err)
