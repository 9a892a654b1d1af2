"""One report for several ablations (``uevavd report DIR1 DIR2 ... --out DIR``): the arms of
ablations run on two days or two machines in one table, one set of paired intervals and one
figure set, when their worlds, contexts and evaluation agree.

Agreeing is checked, not assumed: the same world (the preset's ``[world]`` table, or the same
``--data``), the same recognizer recipe, and the same baseline rows (every reference policy's
final-point numbers per recognizer, setting and split, digit for digit): a baseline reads the
world's contexts, the recognizers' probabilities and the reward, so equal baselines are
equal evaluations. A method at a setting held by two ablations must hold the same rows in
both. A disagreement is refused naming the two folders and what differs.
"""

from __future__ import annotations

import json
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import pandas as pd

from ..atomic import atomic_write, atomic_write_json, write_sealed_json
from .io import ABLATION_FILE, check_outputs, output_digests, read_ablation_meta
from .report_data import is_baseline, recorded_roles


class MergeError(ValueError):
    """Ablations that cannot share a report; the message names the folders and what differs."""


def _read(folder: Path) -> tuple[dict[str, Any], pd.DataFrame, pd.DataFrame]:
    meta = check_outputs(folder, read_ablation_meta(folder / ABLATION_FILE))
    if meta.get("status") != "done":
        raise MergeError(f"{folder}: its ablation is {meta.get('status', 'not finished')!r}, not done: finish it "
                         "(rerun its `uevavd ablate`) before merging")
    results = pd.read_csv(folder / "results.csv", dtype={"setting": str, "method": str, "split": str})
    contexts = (pd.read_csv(folder / "contexts.csv", dtype={"setting": str, "method": str, "split": str,
                                                           "terrain": str})
                if (folder / "contexts.csv").is_file() else pd.DataFrame())
    return meta, results, contexts


def _world(meta: dict[str, Any]) -> Any:
    fp = meta.get("fingerprint") or {}
    preset = fp.get("preset") or {}
    return {"world": preset.get("world"), "data": fp.get("data"), "classifier": preset.get("classifier")}


def _baselines(results: pd.DataFrame) -> pd.DataFrame:
    base = results[is_baseline(results) & results["final"].astype(str).str.lower().isin(("true", "1"))]
    keys = ["method", "recognizer", "seed", "setting", "split"]
    return base.sort_values(keys).reset_index(drop=True)[[*keys, "return", "accuracy", "recognition", "path_m"]]


def _numbers(rows: pd.DataFrame) -> pd.DataFrame:
    keys = ["recognizer", "seed", "split", "episodes", "final"]
    return rows.sort_values(keys).reset_index(drop=True)[[*keys, "return", "accuracy", "path_m"]]


def merge_ablations(folders: Sequence[str | os.PathLike[str]], out: str | os.PathLike[str]) -> Path:
    """Write ``out/results.csv``, ``out/contexts.csv`` and ``out/ablation.json`` holding every
    learned arm of ``folders`` and their shared baselines; returns ``out``. A MergeError when two
    folders' worlds, recognizers or baselines disagree, or one arm is in two folders with other
    numbers."""
    folders = [Path(f) for f in folders]
    if len(folders) < 2:
        raise MergeError("--out merges two or more ablation folders: give them all, e.g. uevavd report A B --out AB")
    out = Path(out)
    if out.resolve() in {f.resolve() for f in folders}:
        raise MergeError(f"--out {out} is one of the folders merged: choose a new folder")
    read = [(f, *_read(f)) for f in folders]
    first, meta0, res0, _ = read[0]
    with recorded_roles(meta0):
        base0 = _baselines(res0)
        seen: dict[tuple[str, str], tuple[Path, pd.DataFrame]] = {}
        rows, ctx = [], []
        for folder, meta, results, contexts in read:
            if _world(meta) != _world(meta0):
                raise MergeError(f"{folder} and {first} ran on other worlds or recognizers (their ablation.json "
                                 "fingerprints differ in the preset's [world], [classifier] or --data): they cannot "
                                 "share a report")
            base = _baselines(results)
            common = base.merge(base0, on=["method", "recognizer", "seed", "setting", "split"], suffixes=("", "_0"))
            if common.empty or not all((common[c] == common[f"{c}_0"]).all() for c in ("return", "accuracy")):
                raise MergeError(f"{folder} and {first} evaluate otherwise: their baselines' final rows differ (other "
                                 "contexts, recognizers or reward settings); they cannot share a report")
            learned = results[~is_baseline(results)]
            keep = []
            for key, sel in learned.groupby(["method", "setting"], sort=False):
                numbers = _numbers(sel)
                if key not in seen:
                    seen[key] = (folder, numbers)
                    keep.append(sel)
                elif not seen[key][1].equals(numbers):  # the same arm twice (a shared default) is kept once
                    raise MergeError(f"{key[0]} at setting {key[1]} is in both {seen[key][0]} and {folder} with other "
                                     "numbers: merge ablations of other methods or settings, or of the same runs")
            rows += keep
            if not contexts.empty:
                mine = {(m, s) for m, s in seen if seen[(m, s)][0] == folder}
                ctx.append(contexts[[(m, s) in mine for m, s in zip(contexts["method"], contexts["setting"],
                                                                     strict=True)]])
        rows.append(res0[is_baseline(res0)])
        _, _, _, ctx0 = read[0]
        if not ctx0.empty:
            ctx.append(ctx0[ctx0["method"].isin(set(res0.loc[is_baseline(res0), "method"]))])
    out.mkdir(parents=True, exist_ok=True)
    merged = pd.concat(rows, ignore_index=True)  # the union of the columns: each folder's swept keys
    atomic_write(out / "results.csv", merged.to_csv(index=False), fsync=True)
    if ctx:
        atomic_write(out / "contexts.csv", pd.concat(ctx, ignore_index=True).to_csv(index=False), fsync=True)
    if (first / "recognizer_audit.json").is_file():
        atomic_write_json(out / "recognizer_audit.json", json.loads((first / "recognizer_audit.json").read_text()))
    meta = {**_merged_meta([(f, m) for f, m, _, _ in read]), "outputs": output_digests(out)}
    write_sealed_json(out / ABLATION_FILE, meta, fsync=True)
    return out


def _merged_meta(metas: list[tuple[Path, dict[str, Any]]]) -> dict[str, Any]:
    """The first folder's record, with every folder's methods, sweeps, components, lineage and
    perception lines, and where each came from."""
    meta = dict(metas[0][1])
    for key in ("methods",):
        meta[key] = list(dict.fromkeys(m for _, x in metas for m in x.get(key) or []))
    for key in ("components", "lineage", "perception", "sweeps", "method_files"):
        merged: dict[str, Any] = {}
        for _, x in metas:
            for k, v in (x.get(key) or {}).items():
                merged[k] = {**merged[k], **v} if isinstance(v, dict) and isinstance(merged.get(k), dict) else v
        meta[key] = merged
    meta["sweep_methods"] = list(dict.fromkeys(m for _, x in metas for m in x.get("sweep_methods") or []))
    meta["merged_from"] = [str(f.resolve()) for f, _ in metas]
    meta["stages"] = {}
    return meta
