"""Acting and learning of the DQN agents (split the way Tianshou splits policy and algorithm).

* :class:`TableLookup` - the observation table as device tensors, for replayed episodes.
* :class:`Learner` - double DQN update on a batch of whole episodes.
* :class:`GreedyPolicy` / :func:`load_policy` - a trained network as a policy for
  :func:`uevavd.env.evaluate.evaluate_policy` (``reset(n)``, ``act(obs)``).

Action masks: the environment's (N, 7, A) mask marks moves that would be clamped at the
grid's edge. The agent never picks a clamped move, greedily or at random, and the TD
target's argmax (double DQN) is taken over allowed actions only, so Q-values of moves
the agent cannot take never leak into its targets.
"""

from __future__ import annotations

import copy
from pathlib import Path
from typing import Any

import torch
import torch.nn.functional as F

from ..data.grid import N_VIEWS, STOP
from ..state.base import InputGateCache
from ..table import ObservationTable
from . import targets as T
from .checkpoint import ARCH_KEYS, load_checkpoint, load_net_state
from .network import QNetwork, build_network
from .replay import EpisodeBatch
from .rundir import RunDir, read_settings, resolve_spec


class TableLookup:
    """Feature lookup for replayed episodes, sharing the environment's device tensors
    (:class:`uevavd.env.batched.EnvTensors`): features (S', 605, D), boxes (S', 605, 4),
    mask (605, 7, A) bool, and ``local`` mapping table scene indices to rows."""

    def __init__(self, tables: Any) -> None:
        self.features, self.boxes, self.mask, self.local = tables.features, tables.boxes, tables.mask, tables.local

    def gather(self, scene: torch.Tensor, views: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """scene (B,) table indices, views (B, L) -> features (B, L, D) float32, boxes (B, L, 4)
        float32, mask (B, L, 7, A) bool."""
        s = self.local[scene][:, None].expand_as(views)
        return self.features[s, views].float(), self.boxes[s, views], self.mask[views]

    def gather_rows(self, scene: torch.Tensor, views: torch.Tensor, seen: torch.Tensor
                    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Like :meth:`gather`, but features and boxes only where ``seen`` (B, L) bool, as
        (N, D) / (N, 4) rows in ``seen.nonzero()`` order; mask (B, L, 7, A) for all."""
        flat = (self.local[scene][:, None] * self.features.shape[1] + views)[seen]
        f = self.features.reshape(-1, self.features.shape[-1]).index_select(0, flat).float()
        return f, self.boxes.reshape(-1, 4).index_select(0, flat), self.mask[views]


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


class Learner:
    """Online and target networks, Adam, and the double-DQN update over episode batches."""

    def __init__(self, net: QNetwork, *, lr: float, gamma: float, grad_clip: float, loss: str = "huber") -> None:
        self.net = net
        self.target = copy.deepcopy(net).requires_grad_(False)
        for m in self.target.modules():  # a deep copy leaves cuDNN's RNN weights in pieces, which
            if isinstance(m, torch.nn.RNNBase):  # it would then compact on every call (no-op on CPU)
                m.flatten_parameters()
        params = self._params = list(net.parameters())
        # fused Adam: one kernel over all parameters, ~3x faster than the per-tensor loop on
        # CPU (16 -> 5 ms per step for the paper-sized GRU agent), same update rule
        fused = all(p.is_floating_point() and p.device.type in ("cpu", "cuda") for p in params)
        self.optimizer = torch.optim.Adam(params, lr=lr, fused=fused or None)
        self.gamma, self.grad_clip, self.loss = gamma, grad_clip, loss
        self.updates = 0
        self._last: tuple = ()  # the last update's tensors, reduced only when stats is read

    def sync_target(self) -> None:
        self.target.load_state_dict(self.net.state_dict())

    def update(self, batch: EpisodeBatch, lookup: TableLookup) -> tuple[float, torch.Tensor]:
        """One gradient step. Returns (loss, per-episode mean |TD error| (B,))."""
        head = self.net.head
        # Only the observations the loss reads are encoded (see needed_observations): o_0..o_L
        # of an episode of L decisions, less o_L when its last decision ended it (always, in
        # this environment), since a terminal transition bootstraps nothing. Padding is
        # neither computed nor gathered (see episode_q). One unroll from the episode start
        # serves Q(s_t, .) and, shifted by one, the online argmax at s_{t+1} (double DQN);
        # the target net evaluates the same observations.
        seen = needed_observations(batch)  # (B, T+1)
        feats, boxes, mask = lookup.gather_rows(batch.scene, batch.views, seen)
        q_all = episode_q(self.net, feats, boxes, seen)
        with torch.no_grad():
            q_next_online = tuple(q[:, 1:] for q in q_all)
            q_next_target = tuple(q[:, 1:] for q in episode_q(self.target, feats, boxes, seen, skip_first=True))
            boot = head.bootstrap(q_next_online, q_next_target, mask[:, 1:])  # (B, T, K)
            y = T.td_target(batch.reward, batch.done, boot, self.gamma)
        q_taken = head.taken(tuple(q[:, :-1] for q in q_all), batch.a_type, batch.a_range)  # (B, T, K)
        w = head.weights(batch.a_type) * batch.valid[..., None].float()
        if self.loss == "huber":
            per = F.smooth_l1_loss(q_taken, y, reduction="none")
        else:
            per = 0.5 * (q_taken - y) ** 2
        loss = (per * w * batch.weight[:, None, None]).sum() / w.sum().clamp_min(1.0)
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        norm = None
        if self.grad_clip > 0:  # clip_grad_norm_, in its two public halves
            params = self._params
            norm = torch.nn.utils.get_total_norm([p.grad for p in params if p.grad is not None], foreach=True)
            # its multiply by a coefficient clamped to exactly 1 changes no bit: skipped where
            # reading the coefficient costs no device sync (CPU), ~0.4 ms of a paper-sized update
            if norm.device.type != "cpu" or bool(self.grad_clip / (norm + 1e-6) < 1.0):
                torch.nn.utils.clip_grads_with_norm_(params, self.grad_clip, norm, foreach=True)
        self.optimizer.step()
        self.updates += 1
        td = ((q_taken.detach() - y).abs() * w).sum((1, 2)) / w.sum((1, 2)).clamp_min(1.0)
        self._last = (td, q_taken.detach(), w, norm)
        return float(loss.detach()), td

    @property
    def stats(self) -> dict[str, float]:
        """The last update's diagnostics, reduced when read (not on every update): ``td_error``
        (mean |TD error|), ``mean_q`` (Q of the taken actions) and, where grad_clip > 0 (which
        computes it anyway), ``grad_norm`` before clipping."""
        if not self._last:
            return {}
        td, q_taken, w, norm = self._last
        out = {"td_error": float(td.mean()), "mean_q": float((q_taken * w).sum() / w.sum().clamp_min(1.0))}
        if norm is not None:
            out["grad_norm"] = float(norm)
        return out


def observed(batch: EpisodeBatch) -> torch.Tensor:
    """(B, T+1) bool: observation t belongs to the episode (t <= its number of decisions)."""
    length = batch.valid.sum(1)
    return torch.arange(batch.views.shape[1], device=length.device)[None] <= length[:, None]


def needed_observations(batch: EpisodeBatch) -> torch.Tensor:
    """(B, T+1) bool, a prefix of each row: the observations a TD update reads.

    Q(o_t, .) is read at every decision t < L (the taken action's value and, for t >= 1,
    the double-DQN bootstrap of decision t - 1). The final observation o_L is read only to
    bootstrap a last decision that did not end the episode; the environment ends every
    episode with a termination (stop, or the move at T_max - 1), so o_L is never read and
    a batch encodes about a quarter fewer observations. The loss is the same as over all
    of o_0..o_L (``tests/policy/test_learner.py``)."""
    length = batch.valid.sum(1)
    last_done = batch.done.gather(1, (length - 1).clamp_min(0)[:, None])[:, 0] & (length > 0)
    upto = length - last_done.to(length.dtype)
    return torch.arange(batch.views.shape[1], device=length.device)[None] <= upto[:, None]


def episode_q(net: QNetwork, feats: torch.Tensor, boxes: torch.Tensor, seen: torch.Tensor,
              *, skip_first: bool = False) -> tuple[torch.Tensor, ...]:
    """Q-values (B, T+1, n) per branch of padded episodes, computed only where ``seen``
    (B, T+1) (zeros elsewhere). ``feats`` (N, D) / ``boxes`` (N, 4) hold the seen rows in
    ``seen.nonzero()`` order. A memoryless estimator reads just those rows (and, with
    ``skip_first``, not o_0); a recurrent one is unrolled from the episode start, over
    packed sequences when it offers ``forward_packed`` (else over the padded batch)."""
    est = net.estimator
    b, t1 = seen.shape
    if not est.recurrent:
        rows = seen
        if skip_first:
            rows = seen.clone()
            rows[:, 0] = False
            keep = rows[seen]
            feats, boxes = feats[keep], boxes[keep]
        s = est(feats[:, None], boxes[:, None])[:, 0]
    elif hasattr(est, "forward_packed"):
        rows = seen
        s = est.forward_packed(feats, boxes, seen)
    else:
        rows = seen
        pf = feats.new_zeros(b, t1, feats.shape[-1])
        pb = boxes.new_zeros(b, t1, 4)
        pf[seen], pb[seen] = feats, boxes
        s = est(pf, pb)[seen]
    out = []
    for q in net.head(s):
        full = q.new_zeros(b, t1, q.shape[-1])
        full[rows] = q
        out.append(full)
    return tuple(out)


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
                 seed: int = 0, features: torch.Tensor | None = None) -> None:
        self.net = net.to(device).eval()
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
    def _input_gates(self, flat: torch.Tensor, boxes: torch.Tensor) -> torch.Tensor:
        """(N, 3H) GRU input gates W_ih g_t + b_ih of the rows at ``flat`` = scene * 605 + view
        with ``boxes`` (N, 4); a row is computed the first time it is seen with that box."""
        est = self.net.estimator
        f = self._features
        if self._gates is None:
            rows = f.shape[0] * f.shape[1]
            self._gates = torch.empty(rows, est.gate_width, device=self.device)
            self._gates_box = torch.full((rows, 4), float("nan"), device=self.device)
        new = (self._gates_box.index_select(0, flat) != boxes).any(1)  # NaN: never computed
        if bool(new.any()):
            idx, box = flat[new], boxes[new]
            f = f.reshape(-1, f.shape[-1])
            for i in range(0, len(idx), 4096):  # bounds the float32 copy of the features
                j = idx[i:i + 4096]
                g = est.encoder(f[j.cpu()].to(self.device).float(), box[i:i + 4096])
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

    def _gru_step(self, flat: torch.Tensor, boxes: torch.Tensor, t: torch.Tensor,
                  hidden: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The estimator's step from cached input gates: s_t (N, state_dim), h_t (N, H)."""
        gates = self._input_gates(flat, boxes)  # a work buffer, which the step may overwrite
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
            if self._features is not None:
                flat = rows(obs["scene"]) * N_VIEWS + rows(obs["view"])
                if self._gru:
                    s, hidden = self._gru_step(flat, boxes, t, hidden)
                else:
                    proj = self._projections(rows(obs["scene"]))
                    img = proj.view(-1, proj.shape[-1]).index_select(0, flat)
                    s, hidden = est.step_encoded(est.encoder.combine(img, boxes), hidden)
                q = self.net.head(s)
            else:
                feats = rows(obs["features"]).float()
                q, hidden = self.net.step(feats, boxes, hidden)
            greedy_type, greedy_range = self.net.head.greedy(q, mask)
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
                with_table: bool = True) -> GreedyPolicy:
    """The greedy policy of a training run directory (its latest checkpoint). With
    ``with_table`` it reads the run's table features to evaluate faster (see GreedyPolicy);
    its actions are the same either way."""

    run_dir = Path(run_dir)
    settings = read_settings(run_dir)
    spec = resolve_spec(run_dir)

    net = build_network(spec.state, spec.head, settings["feature_dim"], n_ranges=settings["env"]["max_range"])
    path = run_dir / weights if weights else RunDir(run_dir).checkpoint
    state = load_checkpoint(path, expect=settings, keys=ARCH_KEYS)  # the network, not a resume
    load_net_state(net, state["net"], path)
    return GreedyPolicy(net, device=device, features=table_features(settings) if with_table else None)


def table_features(settings: dict[str, Any]) -> torch.Tensor | None:
    """The run's table features (S, 605, D) float16 (memory-mapped), or None if not on disk."""
    import numpy as np


    path = settings.get("table_path")
    if not path or not Path(path).is_dir():
        return None
    table = ObservationTable.load(path)
    if table.key != settings.get("table_key"):
        return None
    return torch.from_numpy(np.array(table.features))
