"""Choose the paper64 preset's recipe on training data only.

Each candidate recipe is the probe (``benchmarks/paper64_probe.toml``: 16 of the 20 training
contexts per block trained on, the other 4 held out as the ``validation`` split) with a few
overrides. Every candidate trains MAP, Memo-MAP and IBE-MAP for ``--seeds`` seeds on one
recognizer and is evaluated every 10,000 episodes on its training and validation contexts;
no test split is read. The script prints the validation curve (mean over methods and seeds)
and each method's final validation return, and names the candidate the rule picks:

    the highest mean validation return over the last three evaluations (80k, 90k, 100k episodes),
    methods and seeds pooled; the shortest length is the first evaluation whose pooled
    validation return is within 0.01 of the candidate's best (the plateau).

    python benchmarks/paper64_recipes.py --data WORLD --out DIR [--seeds 2]

WORLD is the 150-context world (``uevavd synth --preset paper64`` writes the same images). Each
candidate is an ordinary ``uevavd ablate`` output folder under DIR, so an interrupted run resumes.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tomllib
from pathlib import Path

import pandas as pd
import tomli_w

PROBE = Path(__file__).resolve().parent / "paper64_probe.toml"

#: Candidate recipes: overrides on top of the probe (the quick preset's recipe).
CANDIDATES: dict[str, dict[str, object]] = {
    "quick-recipe": {},
    "lr3e-4": {"train.lr": 3e-4},
    "wide": {"state.input_dim": 320, "state.state_dim": 256, "head.hidden": 256},
}


def write_preset(name: str, overrides: dict[str, object], out: Path) -> Path:
    with PROBE.open("rb") as f:
        preset = tomllib.load(f)
    preset["name"] = f"paper64-recipe-{name}"
    preset["overrides"].update(overrides)
    path = out / f"{name}.toml"
    path.write_text(tomli_w.dumps(preset))
    return path


def curves(out: Path) -> pd.DataFrame:
    frames = []
    for name in CANDIDATES:
        csv = out / name / "results.csv"
        if csv.is_file():
            df = pd.read_csv(csv)
            df = df[df.split.isin(["train", "validation"])].drop_duplicates(
                ["method", "seed", "episodes", "split", "final"])
            df["candidate"] = name
            frames.append(df)
    return pd.concat(frames) if frames else pd.DataFrame()


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", required=True, help="the 150-context world's root")
    ap.add_argument("--out", required=True, type=Path, help="a folder for the candidates' ablations")
    ap.add_argument("--seeds", type=int, default=2)
    ap.add_argument("--only", nargs="*", default=list(CANDIDATES), help="candidates to run (default: all)")
    ap.add_argument("--report", action="store_true", help="only print the tables of what has run")
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    if not args.report:
        for name in args.only:
            preset = write_preset(name, CANDIDATES[name], args.out)
            cmd = [sys.executable, "-m", "uevavd.cli", "ablate", "--preset", str(preset), "--data", args.data, "--seeds", str(args.seeds),
                   "--recognizers", "1", "--methods", "map", "memo_map", "ibe_map", "--out", str(args.out / name)]
            print("$", " ".join(cmd), flush=True)
            if subprocess.run(cmd).returncode:
                return 1
    df = curves(args.out)
    if df.empty:
        print("nothing has run yet")
        return 1
    df["k"] = (df.episodes / 10_000).round().astype(int) * 10
    per = df[~df.final].groupby(["candidate", "split", "k"])["return"].mean().unstack("k")
    print("\nmean return over methods and seeds, by thousands of episodes:")
    print(per.round(3).to_string())
    val = df[(~df.final) & (df.split == "validation")]
    fin = val[val.k >= 80].groupby(["candidate", "method"])["return"].mean().unstack("method")
    print("\nvalidation return, mean of the evaluations at 80k-100k episodes:")
    print(fin.round(3).to_string())
    score = val[val.k >= 80].groupby("candidate")["return"].mean()
    best = score.idxmax()
    curve = val[val.candidate == best].groupby("k")["return"].mean()
    plateau = int(curve[curve >= curve.max() - 0.01].index.min())
    print(f"\nrule: {best} (pooled validation {score[best]:.3f}); its pooled validation return is within 0.01 "
          f"of its best from {plateau}k episodes on")
    return 0


if __name__ == "__main__":
    sys.exit(main())
