"""Checkpoints of training runs: written atomically, read with ``weights_only=True``.

A finished run also writes ``policy.safetensors``: the online network alone (no optimizer,
no replay buffer), with its method and settings in the header (:func:`save_policy_file`,
:func:`read_policy_file`); that is the file to share.

A checkpoint is a dict of tensors and plain values (``torch.save``): ``meta`` (what it
belongs to: method, spec hash, table key, feature size, action space), the online and
target networks, the optimizer, the replay buffer, the environment's state, the RNG
states, the running episodes and the loop counters. Loading checks ``meta`` against the
run's settings and refuses a checkpoint of another method or other spaces, naming what
differs.
"""

from __future__ import annotations

import errno
import json
import os
import zipfile
from pathlib import Path
from typing import Any

import torch

from ..atomic import atomic_save, atomic_write
from ..hashing import file_sha256, seal, unseal
from ..perception.weights import state_dict_hash
from ..presets import ZOO
from .rundir import RunDir, with_legacy_settings

#: What a checkpoint's network must agree on with whoever loads it (method, table, spaces).
ARCH_KEYS = ("method", "spec_hash", "table_key", "feature_dim", "n_types", "n_ranges", "t_max", "state", "head")
#: What a run's evaluation reads from its settings.json besides the network: checked against the
#: checkpoint, which records the settings the run trained under (an unsealed settings.json with
#: another thre was evaluated under it).
EVAL_KEYS = (*ARCH_KEYS, "env")
#: What a run must agree on to *resume* from a checkpoint: a checkpoint of another seed,
#: other training settings, another torch thread count or another uevavd version would
#: resume into a run that differs from an uninterrupted one.
META_KEYS = (*ARCH_KEYS, "seed", "train", "env", "threads", "uevavd")


class CheckpointError(ValueError):
    """A checkpoint is unreadable or belongs to another method, table or action space."""


def checkpoint_meta(settings: dict[str, Any]) -> dict[str, Any]:
    meta = {k: settings.get(k) for k in META_KEYS}
    meta["uevavd"] = (settings.get("versions") or {}).get("uevavd")
    return meta


def save_checkpoint(path: str | os.PathLike[str], state: dict[str, Any]) -> Path:
    """``torch.save`` to a temp file in the same folder, fsync, then ``os.replace``."""
    try:
        return atomic_write(path, lambda f: torch.save(state, f), fsync=True)
    except RuntimeError as exc:
        if "unexpected pos" in str(exc) or "write" in str(exc).lower():  # torch's words for a failed write
            raise OSError(errno.ENOSPC, "could not write the checkpoint (disk full?): free space and rerun; "
                          "the previous checkpoint is intact", str(path)) from None
        raise


def load_checkpoint(path: str | os.PathLike[str], *, expect: dict[str, Any] | None = None,
                    keys: tuple[str, ...] = META_KEYS) -> dict[str, Any]:
    """Load a checkpoint (CPU tensors). With ``expect`` (a run's settings), refuse one that
    differs in ``keys`` (default: everything a resume must share; :data:`ARCH_KEYS` for
    loading the network alone), listing each difference."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"{path}: no checkpoint there (train first with `uevavd train`)")
    # torch.load ignores the zip records' CRCs: a flipped bit resumed to other weights
    try:
        with zipfile.ZipFile(path) as zf:
            bad = zf.testzip()
    except (zipfile.BadZipFile, OSError) as exc:  # cut short, or not a checkpoint at all: no record to name
        raise CheckpointError(f"{path}: damaged checkpoint (not a readable zip archive: {exc}; a write cut short?); "
                              "delete it to start the run over, or restore it from a copy") from None
    if bad is not None:
        raise CheckpointError(f"{path}: damaged checkpoint (record {bad} fails its CRC); delete it to start the run "
                              "over, or restore it from a copy")
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # noqa: BLE001 - any unpickling failure means unreadable
        raise CheckpointError(f"{path}: unreadable checkpoint ({exc}); delete it to start over") from None
    if not isinstance(state, dict) or "meta" not in state:
        raise CheckpointError(f"{path}: not a uevavd training checkpoint (no meta)")
    if expect is not None:
        want, have = with_legacy_settings(checkpoint_meta(expect)), with_legacy_settings(state["meta"])
        diffs = [f"{k}: checkpoint has {have.get(k)!r}, expected {want[k]!r}"
                 for k in keys if have.get(k) != want[k]]
        if diffs:
            raise CheckpointError(f"{path} belongs to another configuration: " + "; ".join(diffs))
    return state


#: The shareable policy a finished run writes beside its checkpoint.
POLICY_FILE = RunDir(".").policy.name
POLICY_FORMAT = "uevavd-policy/2"
#: The formats a policy file may have: this version's (sealed, always) and the first, whose
#: header no digest protects: read only for the model zoo's own files, whose whole-file sha256
#: its manifests list (:func:`shipped_policy_digests`).
LEGACY_FORMAT = "uevavd-policy/1"
POLICY_FORMATS = (LEGACY_FORMAT, POLICY_FORMAT)
#: The run settings a policy file carries (what loading it must check and rebuild).
POLICY_KEYS = ("method", "spec_hash", "table_key", "table_identity", "feature_dim", "env", "seed")


def save_policy_file(path: str | os.PathLike[str], net_state: dict[str, torch.Tensor], method_toml: str,
                     settings: dict[str, Any]) -> Path:
    """The network's state as ``.safetensors`` with the method TOML and the settings
    :data:`POLICY_KEYS` in its header, written atomically."""
    from safetensors.torch import save_file

    tensors = {k: v.detach().cpu().contiguous() for k, v in net_state.items()}
    # the weights' digest, and the header's own over it (method, settings): both checked on read
    meta = seal({"format": POLICY_FORMAT, "method_toml": method_toml,
                 "settings": json.dumps({k: settings.get(k) for k in POLICY_KEYS}),
                 "weights_hash": state_dict_hash(tensors)})
    return atomic_save(Path(path), lambda tmp: save_file(tensors, tmp, metadata=meta))


def read_policy_file(path: str | os.PathLike[str]) -> tuple[str, dict[str, Any], dict[str, torch.Tensor]]:
    """``(method TOML, settings, network state)`` of a :func:`save_policy_file` file; anything
    else is a one-line error naming the file."""
    from safetensors import SafetensorError, safe_open
    from safetensors.torch import load_file

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no policy file there")
    try:
        with safe_open(str(path), framework="pt") as fh:
            meta = fh.metadata() or {}
        state = load_file(str(path))
    except (SafetensorError, OSError, ValueError) as exc:
        raise CheckpointError(f"{path}: unreadable policy file ({exc})") from None
    if meta.get("format") not in POLICY_FORMATS:
        raise CheckpointError(f"{path}: not a uevavd policy file (format {meta.get('format')!r}, expected one of "
                              f"{list(POLICY_FORMATS)})")
    if meta["format"] == LEGACY_FORMAT and file_sha256(path) not in shipped_policy_digests():
        raise CheckpointError(f"{path}: a {LEGACY_FORMAT} file, whose header no digest protects (an edited method or "
                              "threshold would pass): that format is read only for the model zoo's own files; save the "
                              f"policy again from its run (uevavd.load_run(RUN).save_policy(FILE)) for a sealed "
                              f"{POLICY_FORMAT} file")
    # files of the first format may lack the header's digest (and the oldest the weights'); this
    # format's always carry both, so one without them had them removed
    meta = unseal(meta, str(path), "copy it again, or evaluate the run's checkpoint",
                  legacy=meta["format"] != POLICY_FORMAT)
    if "weights_hash" in meta and state_dict_hash(state) != meta["weights_hash"]:
        raise CheckpointError(f"{path}: damaged (its weights no longer match the weights_hash written with them); "
                              "copy it again, or evaluate the run's checkpoint")
    return meta["method_toml"], json.loads(meta["settings"]), state


def shipped_policy_digests() -> frozenset[str]:
    """The sha256 of every file the package's model zoo manifests list (``model_zoo/pretrained/*/
    manifest.json``): the only first-format policy files this version reads."""
    out: set[str] = set()
    for manifest in sorted((ZOO / "pretrained").glob("*/manifest.json")):
        try:
            out.update(str(rec["sha256"]) for rec in json.loads(manifest.read_text(encoding="utf-8"))["files"].values())
        except (OSError, ValueError, KeyError, TypeError):
            continue  # a damaged manifest vouches for nothing; `uevavd zoo check` names it
    return frozenset(out)


def check_policy_fits(path: str | os.PathLike[str], settings: dict[str, Any], *, table: Any = None,
                      method: str | None = None, env: Any = None) -> None:
    """Refuse a policy file (its header ``settings``) for another method, another table
    config or another action space, naming what differs. ``table``: an observation table it
    would act on; it must have the perception identity the policy was trained with (same
    segmenter, decomposition, encoder and classifier weights; the dataset may differ, so a
    shipped policy acts on a freshly generated world). ``env``: an EnvConfig whose action
    space (``max_range`` ranges of 7 action types) the network must produce."""
    problems = []
    if method is not None and settings.get("method") != method:
        problems.append(f"method: the file holds {settings.get('method')!r}, not {method!r}")
    if table is not None:
        if int(table.feature_dim) != int(settings["feature_dim"]):
            problems.append(f"features: the policy reads {settings['feature_dim']}-d features, the table has "
                            f"{table.feature_dim}-d")
        mine, theirs = settings.get("table_identity") or {}, getattr(table, "perception_identity", {}) or {}
        if mine and theirs:
            problems += [f"{k}: policy {mine.get(k)!r}, table {theirs.get(k)!r}"
                         for k in sorted(set(mine) | set(theirs)) if mine.get(k) != theirs.get(k)]
        elif table.key != settings.get("table_key"):
            problems.append(f"table: trained on table {settings.get('table_key')}, not {table.key}")
    if env is not None and int(env.max_range) != int(settings["env"]["max_range"]):
        problems.append(f"action space: the policy chooses among {settings['env']['max_range']} ranges, the env "
                        f"config has max_range {env.max_range}")
    if problems:
        raise CheckpointError(f"{path} does not fit ({'; '.join(problems)}): use it with the table and env config "
                              "of its own method (the file's header records them)")


def load_net_state(net: torch.nn.Module, state: dict[str, torch.Tensor], path: str | os.PathLike[str]) -> None:
    """``net.load_state_dict(state)``, or a one-line error naming the file and the tensors
    whose names or shapes differ (a policy of another action space or size) instead of
    torch's multi-line message."""
    own = net.state_dict()
    diffs = [f"{k} {tuple(state[k].shape)} vs {tuple(v.shape)}" for k, v in own.items()
             if k in state and tuple(state[k].shape) != tuple(v.shape)]
    missing, extra = sorted(set(own) - set(state)), sorted(set(state) - set(own))
    if diffs or missing or extra:
        parts = ([f"shapes (file vs network): {', '.join(diffs[:3])}"] if diffs else []) + \
            ([f"missing {', '.join(missing[:3])}"] if missing else []) + ([f"unexpected {', '.join(extra[:3])}"]
                                                                        if extra else [])
        raise CheckpointError(f"{path}: its network does not match the method it names ({'; '.join(parts)}); "
                              "it was written for another action space or network size")
    net.load_state_dict(state)
