"""Write docs/results.md: the index of every published result under docs/results/, one table
per result (each method's final return per split, default setting, with its 95 % interval)
under a provenance line (the command as the topic page gives it, the commit and date that
published it, the machine) and links to its report and topic page.

    python benchmarks/results_index.py          # rewrites docs/results.md
    python benchmarks/results_index.py --check  # exit 1 if docs/results.md is not current

The figures come from each folder's summary.csv (what `uevavd report` wrote), the commit and date
from git; the commands (below) are those the topic pages give.
"""

from __future__ import annotations

import argparse
import csv
import re
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
RESULTS = DOCS / "results"
#: The order of the index, and what each group of results answers.
GROUPS = (
    ("The paper's claims on the synthetic world", ("quick-5seeds", "quick-contexts", "quick-contexts-30k", "quick-sam",
                                                   "paper64", "paper64-sweeps", "paper64-300k")),
    ("Generalisation to unseen contexts", ("generalisation-validation", "generalisation-validation-plr",
                                           "generalisation-validation-reco", "generalisation-validation-aug",
                                           "generalisation-validation-aux", "generalisation-quick",
                                           "generalisation-confirm", "generalisation-contexts",
                                           "generalisation-paper64")),
    ("Knowing when not to fly", ("stopping-validation-stop", "stopping-validation-pess",
                                 "stopping-validation-gate-pess", "stopping-quick", "stopping-paper64")),
    ("Where to fly: the pose", ("pose-validation-image", "pose-validation", "pose-quick", "pose-quick-world1",
                                "pose-paper64")),
    ("Past the pose rule", ("rule-validation", "rule-validation-ens", "rule-validation-mirror", "rule-validation-reco",
                            "rule-quick-world2", "rule-quick-world3", "rule-quick-world4", "rule-paper64", "rule-paper64-methods",
                            "mirror-quick-world5", "mirror-quick-world4", "mirror-quick-world2", "mirror-quick-world3",
                            "mirror-paper64", "reco-quick-world6", "reco-quick-world2", "reco-quick-world3",
                            "reco-quick-world4", "reco-quick-world5", "reco-paper64", "reco4-quick-world2",
                            "reco4-quick-world3", "reco4-paper64", "reco4-quick-world7", "reco-paper64-world8",
                            "reco-paper64-world9", "reco-paper64-world2",
                            "reco-paper64-world10")),
    ("The paper's components, ablated", ("components-encoder", "components-segmenter", "components-factorial")),
)
#: Results whose arms are settings of one method: their tables give every setting's row.
ARMS = ("components-encoder", "components-segmenter", "components-factorial")
C = "uevavd ablate --preset quick --methods ibe_map --seeds 5 --recognizers 2"
MACHINE = "2 CPU cores (the development VM, an AMD EPYC)"
V = "--preset benchmarks/generalisation_validation.toml --seeds 3 --recognizers 1"
S = "--preset benchmarks/generalisation_shift_validation.toml --seeds 3 --recognizers 1"
#: Each result's command, as its topic page gives it (DIR: the ablation's folder).
COMMANDS = {
    "quick-5seeds": "uevavd ablate --preset quick --seeds 5 --sweep thre=0.2,0.4,0.6,0.8 --sweep C=0,0.02,0.04,0.06",
    "quick-contexts": "uevavd ablate --preset quick --seeds 5 --sweep env.train_per_block=4,10,20",
    "quick-contexts-30k": "uevavd ablate --preset quick --seeds 5 --recognizers 1 --episodes 30000 "
                          "--sweep env.train_per_block=4,10,20",
    "quick-sam": "uevavd ablate --preset quick --seeds 5 --methods map memo_map ibe_map ibe_map_sam "
                 "--sweep thre=0.2,0.4,0.6,0.8 --sweep C=0,0.02,0.04,0.06",
    "paper64": "uevavd ablate --preset paper64",
    "paper64-sweeps": "uevavd ablate --preset paper64 --seeds 2 --recognizers 1 --sweep thre=0.4,0.6,0.8 "
                      "--sweep C=0,0.04,0.06 --sweep env.train_per_block=4,10,20 --sweep-methods ibe_map",
    "paper64-300k": "uevavd ablate --preset paper64 --episodes 300000 --seeds 2 --recognizers 1",
    "generalisation-validation": f"uevavd ablate {V} --sweep head.kappa=-1,0,2",
    "generalisation-validation-plr": f"uevavd ablate {V} --methods ibe_map ibe_map_plr --sweep-methods ibe_map_plr "
                                     "--sweep train.plr_temperature=0.3,1",
    "generalisation-validation-reco": f"uevavd ablate {V} --methods ibe_map ibe_map_reco",
    "generalisation-validation-aug": f"uevavd ablate {V} --methods ibe_map ibe_map_aug --sweep-methods ibe_map_aug "
                                     "--sweep train.feature_dropout=0.05,0.3",
    "generalisation-validation-aux": f"uevavd ablate {V} --methods ibe_map ibe_map_aux --sweep-methods ibe_map_aux "
                                     "--sweep train.aux_recognition=0.1,2",
    "generalisation-quick": "uevavd ablate --preset quick --methods map memo_map ibe_map ibe_map_ens ibe_map_plr "
                            "ibe_map_reco ibe_map_aug ibe_map_aux --seeds 5 --recognizers 2",
    "generalisation-confirm": "uevavd ablate --preset quick --methods ibe_map ibe_map_aug --sweep-methods ibe_map "
                              "ibe_map_aug --seeds 5 --recognizers 2 --sweep env.train_per_block=4",
    "generalisation-contexts": "uevavd ablate --preset quick --methods ibe_map ibe_map_aug --sweep-methods ibe_map "
                               "ibe_map_aug --seeds 5 --recognizers 2 --sweep env.train_per_block=10,20",
    "generalisation-paper64": "uevavd ablate --preset paper64 --methods map memo_map ibe_map ibe_map_ens ibe_map_plr "
                              "ibe_map_reco ibe_map_aug ibe_map_aux",
    "stopping-validation-stop": f"uevavd ablate {S} --methods ibe_map ibe_map_gate ibe_map_stop --sweep-methods "
                                "ibe_map_stop --sweep train.stop_threshold=0.3,0.7,0.9",
    "stopping-validation-pess": f"uevavd ablate {S} --methods ibe_map ibe_map_pess --sweep-methods ibe_map_pess "
                                "--sweep head.kappa=0,2,4",
    "stopping-validation-gate-pess": f"uevavd ablate {S} --methods ibe_map ibe_map_gate_pess --sweep-methods "
                                     "ibe_map_gate_pess --sweep head.kappa=0,1,2",
    "stopping-quick": "uevavd ablate --preset quick --methods map memo_map ibe_map ibe_map_gate ibe_map_stop "
                      "ibe_map_pess ibe_map_gate_pess --seeds 5 --recognizers 2",
    "stopping-paper64": "uevavd ablate --preset paper64 --methods ibe_map ibe_map_gate ibe_map_stop ibe_map_pess "
                        "ibe_map_gate_pess",
    "pose-validation-image": f"uevavd ablate {S} --methods ibe_map_pose_gate ibe_map_pose_dagger_gate "
                             "--sweep-methods ibe_map_pose_dagger_gate ibe_map_pose_gate --sweep state.image=false",
    "pose-validation": f"uevavd ablate {S} --methods ibe_map_pose_gate ibe_map_boxpose_gate ibe_map_boxpose_dagger_gate "
                       "ibe_map_pose_pays ibe_map_boxpose_pays",
    "pose-quick": "uevavd ablate --preset quick --methods map memo_map ibe_map ibe_map_gate ibe_map_pose "
                  "ibe_map_pose_gate ibe_map_pose_dagger ibe_map_pose_dagger_gate ibe_map_boxpose_gate "
                  "ibe_map_boxpose_dagger_gate ibe_map_pose_pays ibe_map_boxpose_pays --seeds 5 --recognizers 2 "
                  "--sweep env.train_per_block=4",
    "pose-paper64": "uevavd ablate --preset paper64 --methods ibe_map ibe_map_pose_gate ibe_map_pose_dagger_gate "
                    "ibe_map_boxpose_pays ibe_map_boxpose_gate ibe_map_boxpose_dagger_gate ibe_map_pose_pays "
                    "ibe_map_pose ibe_map_pose_dagger",
    "pose-quick-world1": "uevavd ablate --preset quick --world-seed 1 --methods map memo_map ibe_map ibe_map_gate "
                         "ibe_map_pose ibe_map_pose_gate ibe_map_pose_dagger ibe_map_pose_dagger_gate "
                         "ibe_map_boxpose_gate ibe_map_boxpose_dagger_gate ibe_map_pose_pays ibe_map_boxpose_pays "
                         "--seeds 5 --recognizers 2 --sweep env.train_per_block=4",
    "rule-validation": f"uevavd ablate {S} --methods map memo_map ibe_map map_rule memo_map_rule ibe_map_rule "
                       "ibe_map_boxpose_pays ibe_map_boxpose_rule --sweep train.stop_threshold=0.3,0.7 "
                       "--sweep-methods ibe_map_boxpose_rule",
    "rule-validation-ens": f"uevavd ablate {S} --methods ibe_map_boxpose_rule_ens --sweep train.rule_margin=0.02,0.05 "
                           "--sweep-methods ibe_map_boxpose_rule_ens",
    "rule-validation-mirror": f"uevavd ablate {S} --methods ibe_map_boxpose_rule ibe_map_boxpose_rule_mirror",
    "rule-validation-reco": f"uevavd ablate {S} --methods ibe_map_boxpose_rule ibe_map_boxpose_rule_reco "
                            "--sweep train.stop_threshold=0.5,0.7 --sweep-methods ibe_map_boxpose_rule_reco",
    "rule-quick-world2": "uevavd ablate --preset quick --world-seed 2 --methods map memo_map ibe_map map_rule memo_map_rule ibe_map_rule ibe_map_boxpose_pays ibe_map_boxpose_rule ibe_map_boxpose_rule_ens "
                         "--seeds 5 --recognizers 2",
    "rule-quick-world3": "uevavd ablate --preset quick --world-seed 3 --methods map memo_map ibe_map map_rule memo_map_rule ibe_map_rule ibe_map_boxpose_pays ibe_map_boxpose_rule ibe_map_boxpose_rule_ens "
                         "--seeds 5 --recognizers 2",
    "rule-quick-world4": "uevavd ablate --preset quick --world-seed 4 --methods ibe_map_boxpose_rule --seeds 5 --recognizers 2",
    "mirror-quick-world5": "uevavd ablate --preset quick --world-seed 5 --methods ibe_map_boxpose_rule "
                           "ibe_map_boxpose_rule_mirror --seeds 5 --recognizers 2",
    "mirror-quick-world4": "uevavd ablate --preset quick --world-seed 4 --methods ibe_map_boxpose_rule "
                           "ibe_map_boxpose_rule_mirror --seeds 5 --recognizers 2",
    "mirror-quick-world2": "uevavd ablate --preset quick --world-seed 2 --methods ibe_map_boxpose_rule "
                           "ibe_map_boxpose_rule_mirror --seeds 5 --recognizers 2",
    "mirror-quick-world3": "uevavd ablate --preset quick --world-seed 3 --methods ibe_map_boxpose_rule "
                           "ibe_map_boxpose_rule_mirror --seeds 5 --recognizers 2",
    "mirror-paper64": "uevavd ablate --preset paper64 --methods ibe_map_boxpose_rule ibe_map_boxpose_rule_mirror",
    "reco-quick-world6": "uevavd ablate --preset quick --world-seed 6 --methods ibe_map_boxpose_rule "
                         "ibe_map_boxpose_rule_reco --seeds 5 --recognizers 2",
    "reco-quick-world2": "uevavd ablate --preset quick --world-seed 2 --methods ibe_map_boxpose_rule "
                         "ibe_map_boxpose_rule_reco --seeds 5 --recognizers 2",
    "reco-quick-world3": "uevavd ablate --preset quick --world-seed 3 --methods ibe_map_boxpose_rule "
                         "ibe_map_boxpose_rule_reco --seeds 5 --recognizers 2",
    "reco-quick-world4": "uevavd ablate --preset quick --world-seed 4 --methods ibe_map_boxpose_rule "
                         "ibe_map_boxpose_rule_reco --seeds 5 --recognizers 2",
    "reco-quick-world5": "uevavd ablate --preset quick --world-seed 5 --methods ibe_map_boxpose_rule "
                         "ibe_map_boxpose_rule_reco --seeds 5 --recognizers 2",
    "reco4-quick-world2": "uevavd ablate --preset quick --world-seed 2 --methods ibe_map_boxpose_rule "
                          "ibe_map_boxpose_rule_reco --seeds 5 --recognizers 4",
    "reco4-quick-world3": "uevavd ablate --preset quick --world-seed 3 --methods ibe_map_boxpose_rule "
                          "ibe_map_boxpose_rule_reco --seeds 5 --recognizers 4",
    "reco4-paper64": "uevavd ablate --preset paper64 --methods ibe_map_boxpose_rule ibe_map_boxpose_rule_reco "
                     "--recognizers 4",
    "reco4-quick-world7": "uevavd ablate --preset quick --world-seed 7 --methods ibe_map_boxpose_rule "
                          "ibe_map_boxpose_rule_reco --seeds 5 --recognizers 4",
    "reco-paper64": "uevavd ablate --preset paper64 --methods ibe_map_boxpose_rule ibe_map_boxpose_rule_reco",
    "reco-paper64-world8": "uevavd ablate --preset paper64 --world-seed 8 --methods ibe_map_boxpose_rule "
                           "ibe_map_boxpose_rule_reco --seeds 5 --recognizers 2",
    "reco-paper64-world9": "uevavd ablate --preset paper64 --world-seed 9 --methods ibe_map_boxpose_rule "
                           "ibe_map_boxpose_rule_reco --seeds 5 --recognizers 2",
    "reco-paper64-world2": "uevavd ablate --preset paper64 --world-seed 2 --methods ibe_map_boxpose_rule "
                           "ibe_map_boxpose_rule_reco --seeds 5 --recognizers 2",
    "reco-paper64-world10": "uevavd ablate --preset paper64 --world-seed 10 --methods ibe_map_boxpose_rule "
                            "ibe_map_boxpose_rule_reco --seeds 5 --recognizers 2",
    "rule-paper64": "uevavd ablate --preset paper64 --methods ibe_map_boxpose_pays ibe_map_boxpose_rule",
    "rule-paper64-methods": "uevavd ablate --preset paper64 --methods map_rule memo_map_rule ibe_map_rule --out A && "
                            "uevavd ablate --preset paper64 --out B && uevavd report A B",
    "components-encoder": f"{C} --sweep 'perception.encoder={{name=\"resnet18\",weights=\"random\"}},"
                          '{name="resnet50",weights="random"}\'',
    "components-segmenter": f"uevavd train-sam-small W --threads 1 && {C} --sweep perception.segmenter.name=sam",
    "components-factorial": f"{C} --sweep state.name=single_view,gru --sweep perception.decompose=false,true --cross",
}
ORDER = ("map", "memo_map", "ibe_map")
REFERENCES = ("random", "passive", "box_gate", "pose_seek", "departure_ceiling", "departure_ceiling2",
              "visibility_oracle", "oracle")


def _git(*args: str) -> str:
    return subprocess.run(["git", *args], cwd=ROOT, capture_output=True, text=True, check=True).stdout.strip()


def published(folder: str) -> str:
    """The commit that first published the folder's report, and its date."""
    out = _git("log", "--diff-filter=A", "--format=%h %cs", "--", f"docs/results/{folder}/report.md").splitlines()
    return f"published at {out[-1].split()[0]} ({out[-1].split()[1]})" if out else "not committed yet"


def documented(folder: str) -> tuple[str, str]:
    """(page, section): where the docs discuss the folder (its first link there)."""
    for page in sorted(DOCS.glob("*.md")):
        if page.name == "results.md":
            continue
        lines = page.read_text(encoding="utf-8").splitlines()
        at = next((i for i, line in enumerate(lines) if f"results/{folder}/" in line), None)
        if at is not None:
            section = next((lines[i].lstrip("# ").strip() for i in range(at, -1, -1) if lines[i].startswith("#")), "")
            return page.name, section
    return "", ""


def anchor(section: str) -> str:
    text = re.sub(r"[^\w\- ]", "", section.lower()).strip()
    return re.sub(r" ", "-", text)


def table(folder: str) -> list[str]:
    rows = list(csv.DictReader((RESULTS / folder / "summary.csv").open(encoding="utf-8")))
    if folder in ARMS:  # every setting of the learned method, named "method @ setting"
        rows = [{**r, "method": r["method"] if r["setting"] == "default" else f"{r['method']} @ {r['setting']}"}
                for r in rows if r["setting"] == "default" or r["method"] not in REFERENCES]
    rows = [r for r in rows if r["setting"] == "default" or folder in ARMS]
    splits = [s for s in ("train", "validation", "simple", "hard") if any(r["split"] == s for r in rows)]
    methods = sorted({r["method"] for r in rows},
                     key=lambda m: (m in REFERENCES, REFERENCES.index(m) if m in REFERENCES else 0,
                                    ORDER.index(m) if m in ORDER else len(ORDER), m))
    cell = {(r["method"], r["split"]): r for r in rows}
    out = ["| policy | " + " | ".join(splits) + " |", "|---|" + "---|" * len(splits)]
    for m in methods:
        vals = []
        for s in splits:
            r = cell.get((m, s))
            if r is None:
                vals.append("")
            elif r["return_std"] in ("0", "") or float(r["return_ci_lo"]) == float(r["return_ci_hi"]):
                vals.append(f"{float(r['return_mean']):.3f}")
            else:
                vals.append(f"{float(r['return_mean']):.3f} [{float(r['return_ci_lo']):.3f}, "
                            f"{float(r['return_ci_hi']):.3f}]")
        runs = max(int(cell[(m, s)]["n"]) for s in splits if (m, s) in cell)
        out.append(f"| {m} ({runs} run{'s' if runs != 1 else ''}) | " + " | ".join(vals) + " |")
    return out


def measurements() -> list[str]:
    """The index of the speed and cost measurements: each page's "Measurements" sections (those of
    measurements.md) and their subsections, with the commands that measure them."""
    out = ["## Measurements", "",
           "Speed and cost, each under the command that measures it (a script in `benchmarks/` printing",
           "figures and ratios against a baseline measured in the same run), with its machine and date",
           "there:", "", "| page | section | measured by |", "|---|---|---|"]
    for page in sorted(DOCS.glob("*.md")):
        if page.name == "results.md":
            continue
        lines = page.read_text(encoding="utf-8").splitlines()
        start = next((i for i, line in enumerate(lines) if re.match(r"## Measurements", line)), None)
        if start is None:
            continue
        heads = [(i, line.lstrip("# ").strip()) for i, line in enumerate(lines) if i >= start and line.startswith("#")]
        for k, (i, head) in enumerate(heads):
            end = heads[k + 1][0] if k + 1 < len(heads) else len(lines)
            cmds = sorted({("python " if m.group(1).startswith("benchmarks") else "") + m.group(1)
                           for line in lines[i + 1:end]
                           for m in re.finditer(r"(benchmarks/\w+\.py|(?<=`)uevavd [a-z][\w-]*|(?<=^    )uevavd [a-z][\w-]*)",
                                                line)})
            if not cmds and k + 1 < len(heads) and heads[k + 1][0] - i < 6:
                continue  # a heading over its subsections
            out.append(f"| [{page.name}]({page.name}#{anchor(head)}) | {head} | "
                       f"{', '.join(f'`{c}`' for c in cmds[:3]) or 'see the section'} |")
    return out + [""]


def render() -> str:
    lines = [
        "# Results",
        "",
        "Every published result, one table each: the final policies' mean return per split under the",
        "default setting (thre 0.2, C 0.02), with its 95 % interval (the two-stage bootstrap over",
        "recognizers, then seeds; a deterministic policy's value alone), from the folder's",
        "`summary.csv`. Above each table: the command (as its topic page gives it), the commit that",
        "published it and the machine; below it, the folder (the full report, figures, `results.csv`",
        "and `contexts.csv`) and the section that discusses it. Speed and cost are in",
        "[measurements.md](measurements.md) and [cold-start.md](cold-start.md), each under its command. This page is written by",
        "`python benchmarks/results_index.py`; a test checks it is current.",
        "",
    ]
    for title, folders in GROUPS:
        lines += [f"## {title}", ""]
        for folder in folders:
            page, section = documented(folder)
            lines += [f"### {folder}", "", f"`{COMMANDS[folder]} --out DIR` · {published(folder)} · {MACHINE}", ""]
            lines += table(folder)
            lines += ["", f"Files: [results/{folder}/](results/{folder}/report.md) · discussed in "
                          f"[{page}, \"{section}\"]({page}#{anchor(section)})", ""]
    lines += measurements()
    listed = {f for _, fs in GROUPS for f in fs}
    missing = sorted(p.name for p in RESULTS.iterdir() if p.is_dir() and p.name not in listed)
    if missing:
        raise SystemExit(f"docs/results/ holds folders the index does not list: {missing}; add them to GROUPS")
    return "\n".join(lines).rstrip() + "\n"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--check", action="store_true", help="exit 1 if docs/results.md is not current")
    args = parser.parse_args()
    text = render()
    target = DOCS / "results.md"
    if args.check:
        if not target.is_file() or target.read_text(encoding="utf-8") != text:
            print("docs/results.md is not current: run python benchmarks/results_index.py", file=sys.stderr)
            return 1
        return 0
    target.write_text(text, encoding="utf-8")
    print(f"wrote {target}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
