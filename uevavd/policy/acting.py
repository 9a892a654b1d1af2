"""Acting of the DQN agents (Tianshou's "policy" half; learning is in :mod:`.learner`).

* :func:`epsilon_greedy` / :func:`random_actions` - exploration, written once.
* :class:`GreedyPolicy` / :func:`load_policy` - a trained network as a policy for
  :func:`uevavd.env.evaluate.evaluate_policy` (``reset(n)``, ``act(obs)``).
* :func:`policy_network` / :func:`save_network` - a method's network for a table, trained by
  your own code (behaviour cloning on a Minari dataset), written as a policy file that
  :func:`load_policy_file` and ``uevavd evaluate FILE --table T`` read.

Action masks: the environment's (N, 7, A) mask marks moves that would be clamped at the
grid's edge; the agent never picks a clamped move, greedily or at random.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch

from ..config import as_method, loads_method
from ..data.grid import N_VIEWS, STOP
from ..env.config import EnvConfig, make_config
from ..state.base import InputGateCache, estimator_boxes, reads_pose
from ..table import ObservationTable, load_table
from . import targets as T
from .checkpoint import (
    EVAL_KEYS,
    check_policy_fits,
    load_checkpoint,
    load_net_state,
    read_policy_file,
    save_policy_file,
)
from .config import TrainConfig
from .network import QNetwork, build_network
from .rundir import RunDir, read_settings, run_spec


def random_actions(mask: torch.Tensor, generator: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    """Uniform allowed type, then uniform allowed range for it: (N, 7, A) -> (N,), (N,)."""
    a_type = torch.multinomial(T.type_mask(mask).float(), 1, generator=generator)[:, 0]
    a_range = torch.multinomial(T.range_mask(mask, a_type).float(), 1, generator=generator)[:, 0]
    return a_type, a_range


def epsilon_greedy(a_type: torch.Tensor, a_range: torch.Tensor, mask: torch.Tensor, epsilon: float,
                   generator: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    """Exploration, the one place it is written: each row's greedy action is replaced, with
    probability ``epsilon``, by :func:`random_actions` over its allowed actions. The uniform
    and the random actions are drawn for every row, so the random stream does not depend on
    which rows explore (training and a seeded ``GreedyPolicy`` stay reproducible)."""
    explore = torch.rand(a_type.shape[0], generator=generator, device=a_type.device) < epsilon
    r_type, r_range = random_actions(mask, generator)
    return torch.where(explore, r_type, a_type), torch.where(explore, r_range, a_range)


class GreedyPolicy:
    """A Q network acting greedily over allowed actions (optionally epsilon-greedy).

    ``act(obs)`` takes the environment's batched obs dict ("features" (N, D) f32, "box"
    (N, 4), "mask" (N, 7, A) bool, "t" (N,), "scene" (N,) table index, "view" (N,), and
    optionally "done" (N,) bool) and returns (a_type, a_range), (N,) int64. A recurrent
    network's memory restarts wherever ``obs["t"] == 0``.

    Rows with ``obs["done"]`` True (episodes the evaluator has ended) are not computed:
    their memory is left as it was and their action is a placeholder stop, which
    :func:`~uevavd.env.evaluate.evaluate_policy` ignores. Trained policies stop after about
    two of the T_max = 5 decisions, so most rows of the later steps are skipped.

    With ``features`` (the whole table's (S, 605, D) features) and a built-in estimator,
    the policy projects every view of a scene once, when the scene is first seen, and reads those
    projections by ``obs["scene"], obs["view"]``; it then sets ``needs_features = False``
    so the evaluator skips gathering (N, D) features every step (several times faster on
    exhaustive evaluations, same actions). With the built-in GRU estimator it caches one
    step further: g_t depends only on the (scene, view) and the box observed there, so the
    GRU's input gates W_ih g_t + b_ih are computed once per (scene, view) and gathered per
    step, and the cell is evaluated from them (ATen's CPU GRU cell arithmetic, operation for
    operation, so on CPU the actions are bit for bit those of ``nn.GRU``).
    """

    def __init__(self, net: QNetwork, *, device: torch.device | str = "cpu", epsilon: float = 0.0,
                 seed: int = 0, features: torch.Tensor | None = None, features_key: str | None = None) -> None:
        self.net = net.to(device).eval()
        #: the key of the table whose ``features`` the policy reads by (scene, view): evaluating it
        #: on another table is refused (:func:`uevavd.env.evaluate.evaluate_policy`)
        self.features_key = features_key if features is not None else None
        self.device = torch.device(device)
        self.epsilon = epsilon
        self.generator = torch.Generator(device=self.device)
        self.generator.manual_seed(seed)
        self.hidden = self.net.initial_hidden(0, self.device)
        est = net.estimator
        self._features = features if features is not None and hasattr(est, "step_encoded") else None
        self._proj: torch.Tensor | None = None
        self._gates: torch.Tensor | None = None  # (S * 605, 3H) W_ih g + b_ih per (scene, view)
        self._gates_box: torch.Tensor | None = None  # (S * 605, 4) the box each row was computed with
        self._gru = self._features is not None and isinstance(est, InputGateCache) and est.caches_input_gates()
        self._buffers: dict[str, torch.Tensor] = {}
        self.needs_features = self._features is None

    @torch.no_grad()
    def _projections(self, scenes: torch.Tensor) -> torch.Tensor:
        """(S, 605, image_dim) projections, computed for each scene the first time it is seen."""
        f = self._features
        enc = self.net.estimator.encoder
        if self._proj is None:
            self._proj = torch.zeros(f.shape[0], f.shape[1], enc.image_dim, device=self.device)
            self._have = torch.zeros(f.shape[0], dtype=torch.bool)
        todo = [int(i) for i in torch.unique(scenes).cpu() if not self._have[int(i)]]
        for i in range(0, len(todo), 8):
            idx = torch.tensor(todo[i:i + 8])
            self._proj[idx.to(self.device)] = enc.project(f[idx].to(self.device).float())
            self._have[idx] = True
        return self._proj

    @torch.no_grad()
    def _input_gates(self, flat: torch.Tensor, boxes: torch.Tensor, inputs: torch.Tensor) -> torch.Tensor:
        """(N, 3H) GRU input gates W_ih g_t + b_ih of the rows at ``flat`` = scene * 605 + view
        with ``boxes`` (N, 4); a row is computed the first time it is seen with that box, from
        ``inputs``, the estimator's boxes input (the box, and the pose, a function of the view)."""
        est = self.net.estimator
        f = self._features
        if self._gates is None:
            rows = f.shape[0] * f.shape[1]
            self._gates = torch.empty(rows, est.gate_width, device=self.device)
            self._gates_box = torch.full((rows, 4), float("nan"), device=self.device)
        new = (self._gates_box.index_select(0, flat) != boxes).any(1)  # NaN: never computed
        if bool(new.any()):
            idx, box, inp = flat[new], boxes[new], inputs[new]
            f = f.reshape(-1, f.shape[-1])
            for i in range(0, len(idx), 4096):  # bounds the float32 copy of the features
                j = idx[i:i + 4096]
                g = est.encoder(f[j.cpu()].to(self.device).float(), inp[i:i + 4096])
                self._gates[j] = est.input_gates(g)
            self._gates_box[idx] = box
        return torch.index_select(self._gates, 0, flat, out=self._buffer("gi", len(flat), self._gates.shape[1]))

    def _buffer(self, name: str, rows: int, width: int) -> torch.Tensor:
        """A (rows, width) float32 work tensor reused across steps. On CPU a fresh 100 MB
        tensor costs tens of ms in page faults, about as much as the gather that fills it."""
        buf = self._buffers.get(name)
        if buf is None or buf.shape[0] < rows or buf.shape[1] != width:
            buf = self._buffers[name] = torch.empty(rows, width, device=self.device)
        return buf[:rows]

    def _gru_step(self, flat: torch.Tensor, boxes: torch.Tensor, inputs: torch.Tensor, t: torch.Tensor,
                  hidden: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The estimator's step from cached input gates: s_t (N, state_dim), h_t (N, H)."""
        gates = self._input_gates(flat, boxes, inputs)  # a work buffer, which the step may overwrite
        return self.net.estimator.step_from_gates(gates, hidden, from_zero=bool((t == 0).all()), buffer=self._buffer)

    def reset(self, n: int) -> None:
        self.hidden = self.net.initial_hidden(n, self.device)

    @torch.no_grad()
    def act(self, obs: dict[str, Any]) -> tuple[torch.Tensor, torch.Tensor]:
        boxes = torch.as_tensor(obs["box"], device=self.device, dtype=torch.float32)
        full_mask = torch.as_tensor(obs["mask"], device=self.device).bool()
        n = boxes.shape[0]
        if self.hidden.shape[0] != n:
            self.reset(n)
        live = None  # None: every row is live
        if obs.get("done") is not None:
            done = torch.as_tensor(obs["done"], device=self.device)
            if bool(done.any()):
                live = torch.nonzero(~done)[:, 0]

        def rows(x: Any) -> torch.Tensor:
            x = torch.as_tensor(x, device=self.device)
            return x if live is None else x.index_select(0, live)

        a_type = torch.full((n,), STOP, dtype=torch.int64, device=self.device)
        a_range = torch.zeros(n, dtype=torch.int64, device=self.device)
        if live is None or len(live):
            boxes, mask, t = rows(boxes), rows(full_mask), rows(obs["t"])
            hidden = rows(self.hidden)
            keep = t != 0
            if not bool(keep.all()):  # x * 1 is x: skip the copy where no episode restarts
                hidden = hidden * keep[:, None].to(hidden.dtype)
            est = self.net.estimator
            pose = obs.get("pose") if reads_pose(est) else None
            inputs = estimator_boxes(est, boxes, None if pose is None else rows(pose).float())
            if self._features is not None:
                flat = rows(obs["scene"]) * N_VIEWS + rows(obs["view"])
                if self._gru:
                    s, hidden = self._gru_step(flat, boxes, inputs, t, hidden)
                else:
                    proj = self._projections(rows(obs["scene"]))
                    img = proj.view(-1, proj.shape[-1]).index_select(0, flat)
                    s, hidden = est.step_encoded(est.encoder.combine(img, inputs), hidden)
            else:
                s, hidden = est.step(rows(obs["features"]).float(), inputs, hidden)
            q = self.net.head(s)
            allowed = self.net.allowed(mask, boxes, s, view=rows(obs["view"]), t=t)
            greedy_type, greedy_range = self.net.head.greedy(q, allowed)
            if live is None:
                self.hidden, a_type, a_range = hidden, greedy_type, greedy_range
            else:
                self.hidden.index_copy_(0, live, hidden)
                a_type.index_copy_(0, live, greedy_type)
                a_range.index_copy_(0, live, greedy_range)
        if self.epsilon > 0:  # every row, so the random stream does not depend on "done"
            a_type, a_range = epsilon_greedy(a_type, a_range, full_mask, self.epsilon, self.generator)
        return a_type, a_range


def load_policy(run_dir: str | Path, *, device: str = "cpu", weights: str | None = None,
                with_table: bool = True, table: Any = None) -> GreedyPolicy:
    """The greedy policy of a training run directory (its latest checkpoint). With
    ``with_table`` it reads the run's table features to evaluate faster (see GreedyPolicy);
    its actions are the same either way. With ``table`` (an ObservationTable or its folder:
    another table of the run's perception config, other contexts say) it reads that table's
    features instead, and a table of another perception config is refused naming what differs.
    The policy acts on the table it read; evaluating it on another one is refused."""
    run_dir = Path(run_dir)
    settings = read_settings(run_dir)
    spec = run_spec(run_dir)
    if table is not None:
        table = load_table(table)
        check_policy_fits(run_dir, settings, table=table)

    net = method_network(spec, settings["feature_dim"], settings["env"]["max_range"])
    path = run_dir / weights if weights else RunDir(run_dir).checkpoint
    state = load_checkpoint(path, expect=settings, keys=EVAL_KEYS)  # the network and its env, not a resume
    load_net_state(net, state["net"], path)
    if table is not None:
        return GreedyPolicy(net, device=device, features=torch.from_numpy(np.array(table.features)),
                            features_key=table.key)
    features = table_features(settings) if with_table else None
    return GreedyPolicy(net, device=device, features=features, features_key=settings.get("table_key"))


def table_features(settings: dict[str, Any]) -> torch.Tensor | None:
    """The run's table features (S, 605, D) float16 (memory-mapped), or None if not on disk."""
    path = settings.get("table_path")
    if not path or not Path(path).is_dir():
        return None
    table = ObservationTable.load(path)
    if table.key != settings.get("table_key"):
        return None
    return torch.from_numpy(np.array(table.features))


def load_policy_file(path: str | Path, *, table: Any = None, method: str | None = None,
                     device: str = "cpu") -> tuple[GreedyPolicy, EnvConfig]:
    """A policy saved by ``Run.save_policy`` (or shipped in the model zoo):
    ``(GreedyPolicy, EnvConfig)``. With ``table`` (an ObservationTable or its folder), a
    table of another perception config (segmenter, decomposition, encoder or classifier
    weights) is refused naming what differs, and the policy reads the table's features for
    fast evaluation; with ``method``, a file of another method is refused."""
    path = Path(path)
    method_toml, settings, state = read_policy_file(path)
    cfg = make_config(settings["env"])
    table = None if table is None else load_table(table)
    check_policy_fits(path, settings, table=table, method=method, env=cfg)
    spec = loads_method(method_toml, source=str(path))
    net = method_network(spec, settings["feature_dim"], settings["env"]["max_range"])
    load_net_state(net, state, path)
    # a copy: the table is memory-mapped read-only
    features = None if table is None else torch.from_numpy(np.array(table.features))
    return GreedyPolicy(net, device=device, features=features, features_key=None if table is None else table.key), cfg


def policy_network(method: Any, table: Any) -> QNetwork:
    """A fresh network of ``method`` (a name, a TOML path or a MethodSpec) for ``table``'s
    features and the method's action space: ``net(features (B, T, D), boxes (B, T, 4))``
    gives the head's Q branches (the built-in head: type (B, T, 7) and range (B, T, A))."""
    spec = as_method(method)
    return method_network(spec, load_table(table).feature_dim, spec.env.max_range)


def method_network(spec: Any, feature_dim: int, n_ranges: int) -> QNetwork:
    """The network of a method spec as a policy acts with it: its state estimator and head
    (:func:`~uevavd.policy.network.build_network`) and its stop gate (``train.stop_gate``)."""
    gate = spec.get("train.stop_gate", TrainConfig.stop_gate)
    threshold = spec.get("train.stop_threshold", TrainConfig.stop_threshold)
    ensemble = spec.get("train.rule_ensemble", TrainConfig.rule_ensemble)
    margin = spec.get("train.rule_margin", TrainConfig.rule_margin)
    return build_network(spec.state, spec.head, feature_dim, n_ranges=n_ranges).set_stop_gate(
        gate, threshold, ensemble=ensemble, margin=margin)


def save_network(net: QNetwork, path: str | Path, *, method: Any, table: Any) -> Path:
    """Write ``net`` (a :func:`policy_network` of ``method``, trained however you like) as a
    policy file for ``table``'s perception: what a finished run writes as
    ``policy.safetensors``. A network of another architecture is refused here, naming the
    tensors that differ, rather than when the file is read."""
    spec, table = as_method(method), load_table(table)
    load_net_state(policy_network(spec, table), net.state_dict(), path)  # the method's own shapes
    settings = {"method": spec.name, "spec_hash": spec.hash, "table_key": table.key, "seed": None,
                "table_identity": table.perception_identity, "feature_dim": table.feature_dim,
                "env": spec.env.to_dict()}
    return save_policy_file(path, net.state_dict(), spec.to_toml(), settings)
