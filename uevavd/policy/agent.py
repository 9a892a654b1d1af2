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
import json
from pathlib import Path
from typing import Any

import torch
import torch.nn.functional as F

from . import targets as T
from .network import QNetwork
from .replay import EpisodeBatch


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


class Learner:
    """Online and target networks, Adam, and the double-DQN update over episode batches."""

    def __init__(self, net: QNetwork, *, lr: float, gamma: float, grad_clip: float, loss: str = "huber") -> None:
        self.net = net
        self.target = copy.deepcopy(net).requires_grad_(False)
        self.optimizer = torch.optim.Adam(net.parameters(), lr=lr)
        self.gamma, self.grad_clip, self.loss = gamma, grad_clip, loss
        self.updates = 0

    def sync_target(self) -> None:
        self.target.load_state_dict(self.net.state_dict())

    def update(self, batch: EpisodeBatch, lookup: TableLookup) -> tuple[float, torch.Tensor]:
        """One gradient step. Returns (loss, per-episode mean |TD error| (B,))."""
        head = self.net.head
        # Only the observations an episode really had (o_0..o_L, L = its decisions) are
        # encoded: padding is neither computed nor gathered (see episode_q). One unroll over
        # o_0..o_L from the episode start serves Q(s_t, .) and, shifted by one, the online
        # argmax at s_{t+1} (double DQN); the target net evaluates the same observations.
        seen = observed(batch)  # (B, T+1)
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
        if self.grad_clip > 0:
            torch.nn.utils.clip_grad_norm_(self.net.parameters(), self.grad_clip)
        self.optimizer.step()
        self.updates += 1
        td = ((q_taken.detach() - y).abs() * w).sum((1, 2)) / w.sum((1, 2)).clamp_min(1.0)
        return float(loss.detach()), td


def observed(batch: EpisodeBatch) -> torch.Tensor:
    """(B, T+1) bool: observation t belongs to the episode (t <= its number of decisions)."""
    length = batch.valid.sum(1)
    return torch.arange(batch.views.shape[1], device=length.device)[None] <= length[:, None]


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
    (N, 4), "mask" (N, 7, A) bool, "t" (N,), "scene" (N,) table index, "view" (N,)) and
    returns (a_type, a_range), (N,) int64. A recurrent network's memory restarts wherever
    ``obs["t"] == 0``.

    With ``features`` (the whole table's (S, 605, D) features) and a built-in estimator,
    the policy projects every view of a scene once, when the scene is first seen, and reads those
    projections by ``obs["scene"], obs["view"]``; it then sets ``needs_features = False``
    so the evaluator skips gathering (N, D) features every step (several times faster on
    exhaustive evaluations, same actions).
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

    def reset(self, n: int) -> None:
        self.hidden = self.net.initial_hidden(n, self.device)

    @torch.no_grad()
    def act(self, obs: dict[str, Any]) -> tuple[torch.Tensor, torch.Tensor]:
        boxes = torch.as_tensor(obs["box"], device=self.device, dtype=torch.float32)
        mask = torch.as_tensor(obs["mask"], device=self.device).bool()
        t = torch.as_tensor(obs["t"], device=self.device)
        n = boxes.shape[0]
        if self.hidden.shape[0] != n:
            self.reset(n)
        hidden = self.hidden * (t != 0)[:, None].to(self.hidden.dtype)
        if self._features is not None:
            est = self.net.estimator
            scene = torch.as_tensor(obs["scene"], device=self.device)
            img = self._projections(scene)[scene, torch.as_tensor(obs["view"], device=self.device)]
            s, self.hidden = est.step_encoded(est.encoder.combine(img, boxes), hidden)
            q = self.net.head(s)
        else:
            feats = torch.as_tensor(obs["features"], device=self.device, dtype=torch.float32)
            q, self.hidden = self.net.step(feats, boxes, hidden)
        a_type, a_range = self.net.head.greedy(q, mask)
        if self.epsilon > 0:
            explore = torch.rand(n, generator=self.generator, device=self.device) < self.epsilon
            r_type, r_range = random_actions(mask, self.generator)
            a_type = torch.where(explore, r_type, a_type)
            a_range = torch.where(explore, r_range, a_range)
        return a_type, a_range


def load_policy(run_dir: str | Path, *, device: str = "cpu", weights: str = "checkpoint.pt",
                with_table: bool = True) -> GreedyPolicy:
    """The greedy policy of a training run directory (its latest checkpoint). With
    ``with_table`` it reads the run's table features to evaluate faster (see GreedyPolicy);
    its actions are the same either way."""
    from .checkpoint import load_checkpoint
    from .trainer import resolve_spec

    run_dir = Path(run_dir)
    settings_path = run_dir / "settings.json"
    if not settings_path.is_file():
        raise FileNotFoundError(f"{run_dir} is not a training run: no settings.json (train one with `uevavd train`)")
    settings = json.loads(settings_path.read_text(encoding="utf-8"))
    spec = resolve_spec(run_dir)
    from .network import build_network

    net = build_network(spec, settings["feature_dim"], n_ranges=settings["env"]["max_range"])
    state = load_checkpoint(run_dir / weights, expect=settings)
    net.load_state_dict(state["net"])
    return GreedyPolicy(net, device=device, features=table_features(settings) if with_table else None)


def table_features(settings: dict[str, Any]) -> torch.Tensor | None:
    """The run's table features (S, 605, D) float16 (memory-mapped), or None if not on disk."""
    import numpy as np

    from ..perception.table import ObservationTable

    path = settings.get("table_path")
    if not path or not Path(path).is_dir():
        return None
    table = ObservationTable.load(path)
    if table.key != settings.get("table_key"):
        return None
    return torch.from_numpy(np.array(table.features))
