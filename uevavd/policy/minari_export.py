"""Offline-RL and imitation datasets: a policy's episodes on a table's split as a Minari dataset.

    uevavd export-minari TABLE --split hard --policy oracle --episodes 1000 --id uevavd/quick-hard-oracle-v0

The episodes are :class:`~uevavd.env.aod_env.AODEnv`'s, step for step (its observations,
``MultiDiscrete([7, A])`` actions, float rewards, terminations and the same info keys at
every step, so ``minari.load_dataset`` reads them and ``record_infos`` data is there), from
starts drawn uniformly over the split's contexts and views with ``seed``. The policy is one of
the baselines (``oracle``: the class-knowing oracle, ``visibility_oracle``, ``passive``,
``random``) or a trained run's folder (its greedy policy), acting through the same batched
interface as in evaluation.

Portable: the dataset's environment spec names the table by its key, not its path
(``table="<key>"``, which :func:`~uevavd.table.load_table` finds under
``$UEVAVD_CACHE/tables``), so ``minari.load_dataset(id).recover_environment()`` gives a working
env on any machine whose cache holds the table (``uevavd prepare`` builds the same key from the
same data and method), and the dataset itself loads anywhere. The dataset is written into a
hidden temporary folder beside its own and renamed into place when whole: an export killed at
any point leaves no dataset under its id, and its rerun writes it. Needs ``minari`` (``pip
install "uevavd[clients]"``).
"""

from __future__ import annotations

import errno
import os
import re
import shutil
import tempfile
import warnings
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ..atomic import folder_lock, remove_temporaries
from ..env import ENV_ID
from ..env.aod_env import AODEnv
from ..env.baselines import baseline_entries, baseline_names
from ..env.config import EnvConfig, make_config
from ..paths import tables_dir
from ..table import load_table
from ..version import __version__
from .acting import load_policy
from .rundir import read_settings

#: A Minari dataset id as export-minari writes it: ``[namespace/...]name-vN``, each part letters,
#: digits, '_' and '-' (so it cannot name a folder outside the datasets folder).
DATASET_ID = re.compile(r"^(?:[A-Za-z0-9_-]+/)*[A-Za-z0-9_-]*[A-Za-z0-9]-v\d+$")


def check_dataset_id(dataset_id: str) -> str:
    """``dataset_id``, or a ValueError saying what a dataset id must look like."""
    if not DATASET_ID.match(dataset_id or ""):
        raise ValueError(f"--id {dataset_id!r}: expected a dataset id namespace/name-vN (letters, digits, '_' and '-', "
                         "ending in a version), e.g. uevavd/quick-hard-oracle-v0")
    return dataset_id


def make_policy(name_or_run: str, table: Any, config: EnvConfig, seed: int = 0) -> Any:
    """A registered baseline by name (every one ``uevavd evaluate`` shows), or the greedy policy
    of a trained run's folder."""
    if name_or_run in baseline_names():
        entry = next(e for e in baseline_entries() if e.name == name_or_run)
        policy = entry.load()(table=table, config=config, seed=seed)
        if policy is None:
            raise ValueError(f"--policy {name_or_run!r}: this baseline does not run on table {table.key} (e.g. the "
                             "visibility oracle needs visible fractions, the scripted gates training contexts)")
        return policy
    path = Path(name_or_run)
    if not (path / "settings.json").is_file():
        raise ValueError(f"--policy {name_or_run!r}: expected one of {list(baseline_names())} or a trained run's "
                         "folder (one holding settings.json)")
    return load_policy(path, device="cpu", table=table)  # acting on the exported table's features


def policy_env_config(name_or_run: str, overrides: dict[str, Any] | None = None) -> EnvConfig:
    """The env config an export records episodes under: a trained run's own (its reward's thre,
    C, ... as it trained), the paper's defaults for a baseline; ``overrides`` (``env`` keys) win."""
    base = EnvConfig()
    if name_or_run not in baseline_names() and (Path(name_or_run) / "settings.json").is_file():
        base = make_config(read_settings(Path(name_or_run))["env"])
    return base.replace(**overrides) if overrides else base


def _batched_obs(obs: dict[str, Any], info: dict[str, Any]) -> dict[str, torch.Tensor]:
    """One env's observation as the batched interface a policy acts on (a batch of 1)."""
    pose = {"pose": torch.as_tensor(obs["pose"])[None]} if "pose" in obs else {}  # EnvConfig.pose
    return {**pose,
        "features": torch.as_tensor(obs["features"])[None],
        "box": torch.as_tensor(obs["box"])[None],
        "mask": torch.as_tensor(obs["action_mask"].astype(bool))[None],
        "t": torch.tensor([int(obs["t"])]),
        "scene": torch.tensor([int(info["scene"])]),
        "view": torch.tensor([int(info["view"])]),
        "done": torch.tensor([False]),
    }


def collect_episodes(table: Any, split: str, policy: Any, *, episodes: int, seed: int = 0,
                     config: EnvConfig | None = None, progress: bool = True) -> tuple[list[Any], AODEnv]:
    """``episodes`` of ``policy`` on ``split`` as Minari ``EpisodeBuffer`` s, and the env."""
    from minari.data_collector import EpisodeBuffer
    from tqdm.auto import tqdm

    config = config or EnvConfig()
    env = AODEnv(table, split, config)
    rng = np.random.default_rng(seed)
    buffers = []
    for i in tqdm(range(episodes), desc="episodes", disable=not progress):
        scene = int(rng.choice(env.scenes))
        view = int(rng.integers(len(env.table.features[scene])))
        obs, info = env.reset(options={"scene": scene, "view": view})
        observations, actions, rewards, infos = [obs], [], [], [info]
        policy.reset(1)
        done = False
        while not done:
            a_type, a_range = policy.act(_batched_obs(obs, info))
            action = np.array([int(a_type[0]), int(a_range[0])], np.int64)
            obs, reward, done, _, info = env.step(action)
            observations.append(obs)
            actions.append(action)
            rewards.append(reward)
            infos.append(info)
        buffers.append(EpisodeBuffer(
            id=i, options={"scene": scene, "view": view},
            observations={k: np.stack([o[k] for o in observations]) for k in observations[0]},
            actions=np.stack(actions), rewards=rewards, terminations=[False] * (len(rewards) - 1) + [True],
            truncations=[False] * len(rewards),
            infos={k: np.stack([np.asarray(x[k]) for x in infos]) for k in infos[0]},
        ))
    return buffers, env


def dataset_bytes(buffers: list[Any]) -> int:
    """The bytes of the episodes' arrays (observations, actions, rewards, flags, infos): at least
    what Minari's HDF5 file holds of them."""
    total = 0
    for b in buffers:
        for part in (b.observations, b.infos):
            total += sum(np.asarray(v).nbytes for v in part.values())
        total += np.asarray(b.actions).nbytes + 8 * len(b.rewards) + 2 * len(b.terminations)
    return total


def check_room(folder: Path, need: int) -> None:
    """An ``OSError`` (one line; the command adds what to do) where ``need`` bytes cannot be
    written into ``folder``: its disk holds less free space (with a margin for HDF5's own
    records), or the process's file-size limit (``ulimit -f``) is below it."""
    margin = max(1 << 20, need // 10)
    free = shutil.disk_usage(folder).free
    if free < need + margin:
        raise OSError(errno.ENOSPC, f"{folder.parent}: the dataset needs about {_size(need + margin)} and the disk has "
                                    f"{_size(free)} free (or record fewer --episodes)")
    try:
        import resource
    except ImportError:  # not on Windows
        return
    limit = resource.getrlimit(resource.RLIMIT_FSIZE)[0]
    if limit != resource.RLIM_INFINITY and limit < need + margin:
        raise OSError(errno.EFBIG, f"{folder.parent}: the dataset's file needs about {_size(need + margin)}, past this "
                                   f"process's file-size limit of {limit:,} bytes (or record fewer --episodes)")


def _size(n: int) -> str:
    return f"{n / 1e6:,.1f} MB" if n >= 10**6 else f"{n:,} bytes"


@contextmanager
def _datasets_path(out: str | os.PathLike[str] | None):
    """Minari writes under ``$MINARI_DATASETS_PATH``: ``out`` there for the call."""
    if out is None:
        yield
        return
    old = os.environ.get("MINARI_DATASETS_PATH")
    os.environ["MINARI_DATASETS_PATH"] = str(Path(out).resolve())
    try:
        yield
    finally:
        if old is None:
            del os.environ["MINARI_DATASETS_PATH"]
        else:
            os.environ["MINARI_DATASETS_PATH"] = old


def export_minari(table: Any, split: str, policy: str, dataset_id: str, *, episodes: int = 1000, seed: int = 0,
                  config: EnvConfig | None = None, out: str | os.PathLike[str] | None = None,
                  progress: bool = True) -> Any:
    """Write ``dataset_id`` (``namespace/name-v0``) of ``policy``'s episodes; returns the
    ``MinariDataset``. ``out``: the datasets folder (default Minari's, ``$MINARI_DATASETS_PATH``
    or ``~/.minari/datasets``)."""
    import gymnasium as gym
    import minari

    check_dataset_id(dataset_id)
    table = load_table(table)
    if not table.key:
        raise ValueError("the table has no key (it was not written by `uevavd prepare`): a portable dataset names "
                         "its table by key; save it with `uevavd prepare` first")
    config = config or policy_env_config(policy)
    pol = make_policy(policy, table, config, seed)
    if not (tables_dir() / table.key).is_dir():  # checked before any episode is collected
        raise ValueError(f"table {table.key} is not in the table cache {tables_dir()}: a dataset names its table by "
                         "key, and recover_environment() loads it from there; copy the table's folder there (or "
                         "build it there with `uevavd prepare`) first")
    with _dataset_folder(dataset_id, out) as (root, tmp):
        buffers, env = collect_episodes(table, split, pol, episodes=episodes, seed=seed, config=config,
                                        progress=progress)
        check_room(tmp, dataset_bytes(buffers))  # HDF5 crashes (a segfault) on a full disk or past ulimit -f
        spec = gym.spec(ENV_ID)
        portable = gym.envs.registration.EnvSpec(
            id=spec.id, entry_point=spec.entry_point, max_episode_steps=None,
            kwargs={"table": table.key, "split": split, "config": config.to_dict()},
        )
        with _datasets_path(tmp), warnings.catch_warnings():
            warnings.filterwarnings("ignore", message="`author_email` is set to None", category=UserWarning)
            minari.create_dataset_from_buffers(
                dataset_id=dataset_id, buffer=buffers, env=portable, eval_env=portable,
                author="uevavd export-minari", code_permalink=f"uevavd {__version__}",
                algorithm_name=f"uevavd {policy if policy in baseline_names() else 'trained run ' + Path(policy).name}",
                observation_space=env.observation_space, action_space=env.action_space,
                description=f"{episodes} episodes of {policy} on the {split} split of table {table.key} "
                            f"(starts uniform over its contexts and views, seed {seed}). {_rebuild(table)}",
            )
    with _datasets_path(root):
        return minari.load_dataset(dataset_id)


def _rebuild(table: Any) -> str:
    """How to get the dataset's table where it is not in the cache, from what the table records."""
    import json

    config = table.meta.get("config") or {}
    method, data = config.get("method"), config.get("data_root")
    if not method:
        return (f"recover_environment() loads table {table.key} from $UEVAVD_CACHE/tables: copy its folder there.")
    return (f"recover_environment() loads table {table.key} from $UEVAVD_CACHE/tables; to rebuild it: `uevavd prepare "
            f"{data or 'DATA'} --method {method}` with the preset or --set giving its perception "
            f"{json.dumps(config.get('perception'), sort_keys=True)}.")


@contextmanager
def _dataset_folder(dataset_id: str, out: str | os.PathLike[str] | None):
    """Yield ``(datasets folder, temporary datasets folder)`` for one export of ``dataset_id``:
    Minari writes the dataset into the temporary folder (a hidden sibling of the dataset's
    own), which is renamed into place when the block ends without an error. A killed or failed
    export leaves no dataset under the id (one half written loaded as 0 episodes, and blocked
    the rerun); what a killed one left is removed by the next export of the id, which holds the
    id's lock. A dataset already there is refused before any episode is collected."""
    from minari.storage import get_dataset_path

    with _datasets_path(out):
        root = get_dataset_path().resolve()
    final = root / dataset_id

    def busy(lock_file: str) -> ValueError:
        return ValueError(f"--id {dataset_id}: another export-minari is writing it (it holds {lock_file}); wait "
                          "for it, or choose another id")

    with folder_lock(final, busy):
        remove_temporaries(final.parent, final.name)
        if final.exists():
            raise ValueError(f"--id {dataset_id}: {final} already exists; choose another id (or version), or "
                             "remove that folder")
        tmp = Path(tempfile.mkdtemp(dir=final.parent, prefix=f".{final.name}.", suffix=".tmp"))
        try:
            yield root, tmp
            os.replace(tmp / dataset_id, final)
        finally:
            shutil.rmtree(tmp, ignore_errors=True)
