"""A tour of user mistakes and damaged files through the CLI (docs/faults.md): prints, for
each fault, the exit status and the line the user reads: edited run files and policy headers,
a run killed in its first write, flipped bits in a checkpoint and a policy file, an edited
table, a seal removed, files evaluate must not replace, a cut
results.csv, a lock file that is a link, a zoo manifest pointing outside, values out of range,
bad arguments of every command.

    python examples/fault_tour.py
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

from uevavd.config import load_method
from uevavd.presets import load_preset, preset_overrides
from uevavd.table import ObservationTable
from uevavd.testing.policy import toy_table
from uevavd.testing.worlds import write_tiny_world

W = Path(tempfile.mkdtemp(prefix="uevavd-faults-"))
os.environ["UEVAVD_CACHE"] = str(W / "cache")
world = write_tiny_world(W / "world", contexts=(1, 26), train605=True)
table = toy_table(n_train=2, n_hard=1, feature_dim=8).save(W / "table")
SMALL = ["--set", "state.input_dim=24", "--set", "state.box_dim=8", "--set", "state.state_dim=16", "--set", "head.hidden=16",
         "--set", "train.n_envs=16", "--set", "train.batch_size=8", "--set", "train.buffer_episodes=400",
         "--set", "train.learning_starts=40", "--set", "train.epoch_episodes=100", "--set", "train.eval_contexts=1",
         "--set", "train.threads=1"]

PROGRESS_BAR = re.compile(r"\[\d+:\d\d[<,\]]")  # a tqdm line on stderr (its elapsed time), not the message


def run(*args):
    p = subprocess.run([sys.executable, "-m", "uevavd.cli", *map(str, args)], capture_output=True, text=True,
                       env={**os.environ, "UEVAVD_DEBUG": ""}, timeout=600)
    err = [ln for ln in p.stderr.strip().splitlines()
           if ln.strip() and "Warning" not in ln and "warn" not in ln and not PROGRESS_BAR.search(ln)]
    return p.returncode, (err[-1] if err else p.stdout.strip().splitlines()[-1] if p.stdout.strip() else "")


# a finished run to break
rc, out = run("train", "--method", "map", "--table", table, "--episodes", 100, "--out", W / "run", "--no-progress", "--device", "cpu", *SMALL)
assert rc == 0, out
(W / "afile").write_text("x")
bad_toml = W / "bad.toml"
bad_toml.write_text('_base_ = "map"\n[train]\nepisodez = 3\n')
garbage_csv = W / "abl"
garbage_csv.mkdir()
(garbage_csv / "results.csv").write_text("a,b\n1,2\n")
run2 = W / "run2"
shutil.copytree(W / "run", run2)
(run2 / "settings.json").write_text("{not json")
run3 = W / "run3"
shutil.copytree(W / "run", run3)
(run3 / "done.json").unlink()
data = (run3 / "checkpoint.pt").read_bytes()
(run3 / "checkpoint.pt").write_bytes(data[: len(data) // 2])
(W / "empty").mkdir()
(W / "clf.txt").write_text("not a classifier")
toy = toy_table(n_train=2, n_hard=1, feature_dim=8)  # the same table, recorded as built for the quick preset
quick = load_method("map", preset_overrides(load_preset("quick"))).perception.as_dict()
quick_table = ObservationTable.from_arrays(toy.features, toy.probs, toy.boxes, scenes=toy.scenes, targets=toy.targets,
                                           splits=toy.splits, config={"perception": quick}).save(W / "quick_table")
# damaged artefacts, each copied from the finished run and the table above
def flip(path: Path, at: float) -> None:
    data = bytearray(path.read_bytes())
    data[int(len(data) * at)] ^= 0x10
    path.write_bytes(bytes(data))


run4 = W / "run4"
shutil.copytree(W / "run", run4)
(run4 / "done.json").unlink()
flip(run4 / "checkpoint.pt", 0.3)
flipped_policy = W / "flipped.safetensors"
shutil.copy(W / "run" / "policy.safetensors", flipped_policy)
flip(flipped_policy, 0.9)
edited = W / "edited_table"
shutil.copytree(table, edited)
visible = __import__("numpy").load(edited / "visible.npy")
visible[0, 0] = 7.0
__import__("numpy").save(edited / "visible.npy", visible)
run5 = W / "run5"
shutil.copytree(W / "run", run5)
(run5 / "settings.json").write_text("[1, 2]")
# edited run files: each carries a digest written with it
run6 = W / "run6"
shutil.copytree(W / "run", run6)
(run6 / "settings.json").write_text((run6 / "settings.json").read_text().replace('"thre": 0.2', '"thre": 0.3'))
run7 = W / "run7"
shutil.copytree(W / "run", run7)
(run7 / "method.toml").write_text((run7 / "method.toml").read_text().replace("hidden = 16", "hidden = 17"))
header_policy = W / "header.safetensors"
_st = __import__("safetensors.torch", fromlist=["load_file"])
with __import__("safetensors").safe_open(str(W / "run" / "policy.safetensors"), framework="pt") as fh:
    _meta = dict(fh.metadata())
_meta["settings"] = _meta["settings"].replace('"seed": 0', '"seed": 1')
_st.save_file(_st.load_file(str(W / "run" / "policy.safetensors")), str(header_policy), metadata=_meta)
killed_first = W / "killed_first"  # a train killed while writing its first file
killed_first.mkdir()
(killed_first / ".settings.json.k1ll3d.tmp").write_text('{"env": ')
(W / "loops").mkdir()
os.symlink(".", W / "loops" / "a")
os.symlink("a", W / "loops" / "027")
# a seal removed, files evaluate must not replace, a cut results.csv (another run's records copied in are
# refused where ablate reads them: tests/policy/test_file_digests.py)
unsealed = W / "unsealed"
shutil.copytree(W / "run", unsealed)
_settings = __import__("json").loads((unsealed / "settings.json").read_text())
_settings.pop("sha256")
_settings["env"]["thre"] = 0.3
(unsealed / "settings.json").write_text(__import__("json").dumps(_settings))
cut = W / "cut"
cut.mkdir()
_text = "method,seed,setting,thre,C,episodes,final,split,return,accuracy,recognition,path_m,path_steps,stop_rate,steps,wall_s\n"
(cut / "results.csv").write_text(_text + "map,0,default,0.2,0.02,100,True,hard,0.1,0.5,0.6,10,1,1,1,1\nmap,1,default,0.2")
(W / ".locked.lock").symlink_to(W / "afile")
zoo = W / "zoo"
shutil.copytree(__import__("uevavd.zoo", fromlist=["Zoo"]).Zoo.load("quick").root, zoo)
_manifest = __import__("json").loads((zoo / "manifest.json").read_text())
_manifest["files"]["/etc/hostname"] = {"sha256": "0" * 64, "bytes": 1}
(zoo / "manifest.json").write_text(__import__("json").dumps(_manifest))
cases = [
 ("evaluate a run whose settings.json lost its digest and has thre 0.3", ["evaluate", unsealed, "--table", table, "--split", "hard"]),
 ("evaluate --json over a table's meta.json", ["evaluate", W / "run", "--table", table, "--split", "hard", "--json", table / "meta.json"]),
 ("report on a results.csv cut mid-row", ["report", cut]),
 ("train into a folder whose lock file is a symbolic link", ["train", "--method", "map", "--table", table, "--out", W / "locked", "--episodes", 100, *SMALL]),
 ("zoo check on a manifest naming /etc/hostname", ["zoo", "check", "--zoo", zoo]),
 ("a finite but huge PER priority floor", ["train", "--method", "map", "--table", table, "--out", W / "r13", "--set", "train.per_eps=1e308"]),
 ("a stop gate that does not exist", ["train", "--method", "map", "--table", table, "--out", W / "r14", "--set", "train.stop_gate=\"boxx\""]),
 ("a holdout block that holds out every training context", ["train", "--method", "map", "--table", table, "--out", W / "r15", "--set", "env.holdout_block=1", *SMALL]),
 ("evaluate a run whose settings.json was edited (thre 0.2 -> 0.3)", ["evaluate", run6, "--table", table, "--split", "hard"]),
 ("evaluate a run whose method.toml was edited", ["evaluate", run7, "--table", table, "--split", "hard"]),
 ("evaluate a policy file whose header was edited", ["evaluate", header_policy, "--table", table, "--split", "hard"]),
 ("train into a run killed while writing its first file", ["train", "--method", "map", "--table", table, "--out", killed_first, "--episodes", 100, "--no-progress", "--device", "cpu", *SMALL]),
 ("resuming from a checkpoint with one flipped bit", ["train", "--method", "map", "--table", table, "--out", run4, "--episodes", 100, "--no-progress", "--device", "cpu", *SMALL]),
 ("evaluate a policy file with one flipped bit", ["evaluate", flipped_policy, "--table", table, "--split", "hard"]),
 ("evaluate on a table whose visible.npy was edited", ["evaluate", W / "run", "--table", edited, "--split", "hard"]),
 ("train on a run folder whose settings.json is a JSON list", ["train", "--method", "map", "--table", table, "--out", run5, "--episodes", 100, *SMALL]),
 ("an infinite learning rate", ["train", "--method", "map", "--table", table, "--out", W / "r8", "--set", "train.lr=inf"]),
 ("a head with zero hidden units", ["train", "--method", "map", "--table", table, "--out", W / "r9", "--set", "head.hidden=0"]),
 ("a negative state size", ["train", "--method", "map", "--table", table, "--out", W / "r10", "--set", "state.state_dim=-4"]),
 ("a seed of 1e20", ["train", "--method", "map", "--table", table, "--out", W / "r11", "--seed", "1e20"]),
 ("--max-epochs 0", ["train", "--method", "map", "--table", table, "--out", W / "r12", "--max-epochs", 0]),
 ("synth with seed -1", ["synth", "--out", W / "s3", "--seed", -1, "--contexts", 1]),
 ("synth with an empty context list", ["synth", "--out", W / "s4", "--contexts", ""]),
 ("synth with 1000 workers for one scene", ["synth", "--out", W / "s5", "--contexts", 1, "--size", 16, "--workers", 1000]),
 ("prepare with --threads -2", ["prepare", world, "--method", "map", "--threads", -2]),
 ("prepare on a root holding two self-links", ["prepare", W / "loops", "--method", "map"]),
 ("ablate --sweep thre on a method the preset does not sweep", ["ablate", "--methods", "map", "--sweep", "thre=0.4", "--out", W / "a5"]),
 ("ablate --episodes 0", ["ablate", "--methods", "map", "--episodes", 0, "--out", W / "a6"]),
 ("ablate with a billion seeds", ["ablate", "--seeds", 1000000000, "--out", W / "a7"]),
 ("a table folder that does not exist", ["train", "--method", "map", "--table", W / "nope", "--out", W / "r1"]),
 ("an unknown method", ["train", "--method", "mapp", "--table", table, "--out", W / "r2"]),
 ("a method file with a misspelled key", ["train", "--method", bad_toml, "--table", table, "--out", W / "r3"]),
 ("a negative learning rate", ["train", "--method", "map", "--table", table, "--out", W / "r4", "--set", "train.lr=-1"]),
 ("a reward constant of the wrong type", ["train", "--method", "map", "--table", table, "--out", W / "r5", "--set", "env.thre=\"abc\""]),
 ("--out is an existing file", ["train", "--method", "map", "--table", table, "--out", W / "afile", "--episodes", 100, *SMALL]),
 ("training on a CUDA device that is not there", ["train", "--method", "map", "--table", table, "--out", W / "r6", "--device", "cuda", "--episodes", 100, *SMALL]),
 ("resuming from a half-written checkpoint", ["train", "--method", "map", "--table", table, "--out", run3, "--episodes", 100, "--no-progress", "--device", "cpu", *SMALL]),
 ("a quick-preset table trained without --preset", ["train", "--method", "map", "--table", quick_table, "--out", W / "r7"]),
 ("evaluate on a folder that is not a run", ["evaluate", W / "empty", "--split", "hard"]),
 ("evaluate a run whose settings.json is corrupt", ["evaluate", run2, "--split", "hard"]),
 ("prepare on a file instead of a dataset root", ["prepare", W / "afile", "--method", "map"]),
 ("prepare with a classifier file that is not one", ["prepare", world, "--method", "map", "--classifier", W / "clf.txt"]),
 ("validate an empty folder", ["validate", W / "empty"]),
 ("a Lite0 recognizer on 16 px crops", ["train-classifier", world, "--arch", "efficientnet_lite0", "--epochs", 1, "--out", W / "c.safetensors"]),
 ("a classifier output that is not .safetensors", ["train-classifier", world, "--out", W / "c.pt"]),
 ("synth with a crop size below 16 px", ["synth", "--out", W / "s1", "--size", 8, "--contexts", 1]),
 ("synth with context ids out of range", ["synth", "--out", W / "s2", "--contexts", "0-3"]),
 ("ablate with an unknown preset", ["ablate", "--preset", "quik", "--out", W / "a1"]),
 ("synth into a path that is a file", ["synth", "--out", W / "afile", "--contexts", "1", "--size", 16]),
 ("ablate sweeping a key that is not sweepable", ["ablate", "--sweep", "gamma=0.5", "--out", W / "a2"]),
 ("ablate with zero seeds", ["ablate", "--seeds", 0, "--out", W / "a3"]),
 ("ablate with zero recognizers", ["ablate", "--recognizers", 0, "--out", W / "a4"]),
 ("ablate into a non-empty folder that holds no ablation", ["ablate", "--out", W / "world"]),
 ("report on a results.csv without the expected columns", ["report", garbage_csv]),
 ("report on a folder without results", ["report", W / "empty"]),
]
for what, args in cases:
    rc, line = run(*args)
    print(f"{rc} | {what} | {line.replace(str(W), 'W')[:220]}", flush=True)
shutil.rmtree(W, ignore_errors=True)
