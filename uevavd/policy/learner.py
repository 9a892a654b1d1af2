"""Learning of the DQN agents (Tianshou's "algorithm" half; acting is in :mod:`.acting`).

* :class:`FeatureLookup` - the observation table as device tensors, for replayed episodes.
* :class:`FeatureDropout` / :class:`RecognitionProbe` - the optional augmentation of the
  features an update reads, and the optional auxiliary objective on the state (the mirror's
  augmentation is in :mod:`.mirror`).
* :class:`Learner` - the double-DQN update on a batch of whole episodes, with
  :func:`needed_observations` (what a batch encodes) and :func:`episode_q` (Q over episodes).

The TD target's argmax (double DQN) is taken over allowed actions only (the environment's
(N, 7, A) mask marks moves that would be clamped at the grid's edge), so Q-values of moves
the agent cannot take never leak into its targets.
"""

from __future__ import annotations

import copy
from typing import Any

import torch
import torch.nn.functional as F

from ..env.gate import box_visible
from ..env.oracle import flight_pays
from ..state.base import estimator_boxes, reads_pose
from . import targets as T
from .imitation import OracleLabels, imitation_loss
from .mirror import MirrorAugment
from .network import PROBED_GATES, TRAINING_GATES, QNetwork
from .replay import EpisodeBatch


class FeatureLookup:
    """Feature lookup for replayed episodes, sharing the environment's device tensors
    (:class:`uevavd.env.batched.EnvTensors`): features (S', 605, D), boxes (S', 605, 4),
    mask (605, 7, A) bool, pose (605, 3) metres, and ``local`` mapping table scene indices to rows."""

    def __init__(self, tensors: Any) -> None:
        self.features, self.boxes, self.mask, self.local = tensors.features, tensors.boxes, tensors.mask, tensors.local
        self.reco, self.pose = tensors.reco, tensors.pose

    def recognized_rows(self, scene: torch.Tensor, views: torch.Tensor, seen: torch.Tensor) -> torch.Tensor:
        """(N,) bool: the recognizer recognises each view where ``seen``, in ``seen.nonzero()`` order."""
        return self.reco[self.local[scene][:, None].expand_as(views)[seen], views[seen]]

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

    def pose_rows(self, views: torch.Tensor, seen: torch.Tensor) -> torch.Tensor:
        """(N, 3) the pose in metres of the views where ``seen``, in ``seen.nonzero()`` order."""
        return self.pose.index_select(0, views[seen])


class PaysLabels:
    """Where a flight pays, as a gate's training answer: ``pays`` (T_max, S', 605) bool, at
    index k whether, with k + 1 decisions left, flying from a view of a local scene pays.
    Computed once per run from the table and the env config alone."""

    pays: torch.Tensor
    local: torch.Tensor
    t_max: int

    def at(self, scene: torch.Tensor, view: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        """(N,) table scene indices, views and step indices t (0..T_max - 1) -> (N,) bool."""
        return self.pays[(self.t_max - 1 - t).clamp_min(0), self.local[scene], view]

    def episodes(self, scene: torch.Tensor, views: torch.Tensor) -> torch.Tensor:
        """scene (B,), views (B, L) of decisions t = 0..L-1 -> (B, L) bool (False where t >= T_max)."""
        return self.per_decision(self.pays, scene, views)

    def per_decision(self, values: torch.Tensor, scene: torch.Tensor, views: torch.Tensor) -> torch.Tensor:
        """``values`` laid out as ``pays`` (T_max, S', 605), read at the decisions t = 0..L-1
        of episodes: scene (B,), views (B, L) -> (B, L), zero (False) where t >= T_max."""
        t = torch.arange(views.shape[1], device=views.device)[None].expand_as(views)
        v = values[(self.t_max - 1 - t).clamp_min(0), self.local[scene[:, None].expand_as(views)], views]
        return torch.where(t < self.t_max, v, torch.zeros((), dtype=v.dtype, device=v.device))


class FlightPays(PaysLabels):
    """Where a flight pays (``train.stop_gate = "pays"``): whether the oracle's best reachable
    return from the view beats stopping there (:func:`uevavd.env.oracle.flight_pays`)."""

    def __init__(self, tensors: Any) -> None:
        cfg = tensors.config
        self.pays = torch.as_tensor(flight_pays(tensors.reco.cpu().numpy(), cfg), device=tensors.device)
        self.local, self.t_max = tensors.local, cfg.t_max


class FeatureDropout:
    """Augmentation of the table's features in the updates (``train.feature_dropout``): each
    feature of each gathered row zeroed with probability ``feature_dropout`` and the rest scaled
    by ``1 / (1 - feature_dropout)``, from its own generator (saved with the run, so a resumed run draws the
    same masks). The online and the target network read the same augmented rows; acting reads
    the features as they are."""

    def __init__(self, feature_dropout: float, *, seed: int, device: torch.device | str) -> None:
        self.feature_dropout = float(feature_dropout)
        self.generator = torch.Generator(device=device)
        self.generator.manual_seed(seed)

    def __call__(self, feats: torch.Tensor) -> torch.Tensor:
        keep = torch.rand(feats.shape, generator=self.generator, device=feats.device) >= self.feature_dropout
        return feats * keep / (1.0 - self.feature_dropout)

    def state_dict(self) -> dict[str, Any]:
        return {"rng": self.generator.get_state()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.generator.set_state(state["rng"])


class RecognitionProbe(torch.nn.Module):
    """An auxiliary objective (``train.aux_recognition``): a linear probe on the state s_t
    predicts whether the recognizer recognises the current view (the reward's recognition
    term, ``EnvConfig.recognized``), by binary cross-entropy added to the TD loss with weight
    ``weight`` (the option's value). It shapes the state only: acting never reads it, and it is not part of the
    policy's network (its weights stay in the run's checkpoint)."""

    def __init__(self, state_dim: int, weight: float) -> None:
        super().__init__()
        self.linear = torch.nn.Linear(state_dim, 1)
        self.weight = float(weight)

    def loss(self, s: torch.Tensor, recognized: torch.Tensor) -> torch.Tensor:
        return F.binary_cross_entropy_with_logits(self.linear(s)[:, 0], recognized.float())


class StopProbeLearner:
    """Trains the network's stop probe (``train.stop_gate = "learned"``) with its own Adam: the
    binary cross-entropy of predicting, from the detached state s_t, whether the recognizer
    recognises the current view. The probe reads the state but trains nothing under it, so the
    Q network's updates are those of the same method without the gate."""

    def __init__(self, net: QNetwork, *, lr: float) -> None:
        self.net = net
        self.optimizer = torch.optim.Adam(net.stop_probe.parameters(), lr=lr)

    def update(self, s: torch.Tensor, recognized: torch.Tensor, *, gain: torch.Tensor | None = None,
               weight: torch.Tensor | None = None) -> float:
        """One step on rows ``s`` (N, state_dim): the binary answer ``recognized`` (N,); or, for
        the rule gate's ensemble, each member's squared error on ``gain`` (N,) weighted by its
        resample's ``weight`` (N, K) (how often the row's context was drawn)."""
        if gain is None:
            logits = self.net.stop_probe(s.detach())[:, 0]
            loss = F.binary_cross_entropy_with_logits(logits, recognized.float())
        else:
            err = (self.net.stop_probe(s.detach()) - gain[:, None]) ** 2
            loss = (err * weight).sum() / weight.sum().clamp_min(1.0)
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        self.optimizer.step()
        return float(loss.detach())

    def state_dict(self) -> dict[str, Any]:
        return self.optimizer.state_dict()

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.optimizer.load_state_dict(state)


class Learner:
    """Online and target networks, Adam, and the double-DQN update over episode batches."""

    def __init__(self, net: QNetwork, *, lr: float, gamma: float, grad_clip: float, loss: str = "huber",
                 feature_dropout: FeatureDropout | None = None, aux_recognition: RecognitionProbe | None = None,
                 imitation: OracleLabels | None = None, pays: PaysLabels | None = None,
                 mirror: MirrorAugment | None = None) -> None:
        self.net = net
        if mirror is not None and imitation is not None:
            raise ValueError("mirror= with imitation=: the expert's labels are not mirrored")
        self.mirror = mirror
        if net.stop_gate in PROBED_GATES and pays is None:
            raise ValueError(f'stop_gate "{net.stop_gate}" trains on where a flight pays: pass pays= '
                             '(FlightPays(env.tensors), RulePays(env.tensors, moves))')
        self.pays = pays  # where a flight pays (train.stop_gate "pays"): opens the gate, trains its probe
        self.imitation = imitation  # the expert's labels (train.imitation), read where update(imitate=True)
        self.feature_dropout, self.aux_recognition = feature_dropout, aux_recognition
        self.stop_probe = StopProbeLearner(net, lr=lr) if net.stop_probe is not None else None
        self.target = copy.deepcopy(net).requires_grad_(False)
        for m in self.target.modules():  # a deep copy leaves cuDNN's RNN weights in pieces, which
            if isinstance(m, torch.nn.RNNBase):  # it would then compact on every call (no-op on CPU)
                m.flatten_parameters()
        params = self._params = net.q_parameters() + (
            list(aux_recognition.parameters()) if aux_recognition is not None else [])
        # fused Adam: one kernel over all parameters, ~3x faster than the per-tensor loop on
        # CPU (16 -> 5 ms per step for the paper-sized GRU agent), same update rule
        fused = all(p.is_floating_point() and p.device.type in ("cpu", "cuda") for p in params)
        self.optimizer = torch.optim.Adam(params, lr=lr, fused=fused or None)
        self.gamma, self.grad_clip, self.loss = gamma, grad_clip, loss
        self.updates = 0
        self._last: tuple = ()  # the last update's tensors, reduced only when stats is read

    def sync_target(self) -> None:
        self.target.load_state_dict(self.net.state_dict())

    def parts(self) -> dict[str, Any]:
        """The optional parts a checkpoint holds besides the networks and the optimizer."""
        return {k: v for k, v in (("feature_dropout", self.feature_dropout), ("aux_recognition", self.aux_recognition),
                                  ("stop_probe", self.stop_probe), ("mirror", self.mirror)) if v is not None}

    def update(self, batch: EpisodeBatch, lookup: FeatureLookup, *, imitate: bool = False
               ) -> tuple[float, torch.Tensor]:
        """One gradient step. Returns (loss, per-episode mean |TD error| (B,)); with ``imitate``
        (DAgger, ``train.imitation``), the step minimises the cross-entropy with the expert's
        labels instead, and the per-episode errors are that cross-entropy."""
        head = self.net.head
        # Only the observations the loss reads are encoded (see needed_observations): o_0..o_L
        # of an episode of L decisions, less o_L when its last decision ended it (always, in
        # this environment), since a terminal transition bootstraps nothing. Padding is
        # neither computed nor gathered (see episode_q). One unroll from the episode start
        # serves Q(s_t, .) and, shifted by one, the online argmax at s_{t+1} (double DQN);
        # the target net evaluates the same observations.
        seen = needed_observations(batch)  # (B, T+1)
        feats, boxes, mask = lookup.gather_rows(batch.scene, batch.views, seen)
        if self.feature_dropout is not None:
            feats = self.feature_dropout(feats)
        views, a_type = batch.views, batch.a_type  # as the update sees them: mirrored where train.mirror draws it
        if self.mirror is not None:
            flip = self.mirror.draw(len(batch.scene))
            views, a_type = self.mirror.apply(flip, batch.views, batch.a_type)
            boxes, mask = self.mirror.boxes(boxes, flip[:, None].expand_as(seen)[seen]), lookup.mask[views]
        est = self.net.estimator  # the estimator's input: the box, and the pose where it reads one
        inputs = estimator_boxes(est, boxes, lookup.pose_rows(views, seen) if reads_pose(est) else None)
        q_all, s = episode_q(self.net, feats, inputs, seen, with_state=True)
        if imitate:
            assert self.imitation is not None, "imitate=True on a learner without the expert's labels"
            decides = batch.valid
            if self.net.stop_gate in ("box", "pays"):  # where the gate closes it decides (stop), not the student
                seen_boxes = boxes.new_zeros(*seen.shape, 4)
                seen_boxes[seen] = boxes
                open_ = ~box_visible(seen_boxes[:, :-1])
                if self.pays is not None:
                    open_ = open_ | self.pays.episodes(batch.scene, batch.views[:, :-1])
                decides = decides & open_
            loss, td = imitation_loss(q_all, *self.imitation.labels(batch.scene, batch.views), decides,
                                      batch.weight)
            return self._finish(loss, s, seen, batch, lookup, td, None, None, boxes)
        with torch.no_grad():
            q_next_online = tuple(q[:, 1:] for q in q_all)
            q_next_target = tuple(q[:, 1:] for q in episode_q(self.target, feats, inputs, seen, skip_first=True))
            if self.net.stop_gate in TRAINING_GATES:  # the next decision's allowed actions, as acting saw them
                seen_boxes = boxes.new_zeros(*seen.shape, 4)
                seen_boxes[seen] = boxes
                pays = self.pays.episodes(batch.scene, batch.views) if self.pays is not None else None
                steps = torch.arange(seen.shape[1], device=seen.device)[None].expand_as(batch.views)
                mask = self.net.allowed(mask, seen_boxes, training=True, pays=pays, view=views, t=steps)
            boot = head.bootstrap(q_next_online, q_next_target, mask[:, 1:])  # (B, T, K)
            y = T.td_target(batch.reward, batch.done, boot, self.gamma)
        q_taken = head.taken(tuple(q[:, :-1] for q in q_all), a_type, batch.a_range)  # (B, T, K)
        w = head.weights(a_type) * batch.valid[..., None].float()
        if self.loss == "huber":
            per = F.smooth_l1_loss(q_taken, y, reduction="none")
        else:
            per = 0.5 * (q_taken - y) ** 2
        loss = (per * w * batch.weight[:, None, None]).sum() / w.sum().clamp_min(1.0)
        td = ((q_taken.detach() - y).abs() * w).sum((1, 2)) / w.sum((1, 2)).clamp_min(1.0)
        return self._finish(loss, s, seen, batch, lookup, td, q_taken.detach(), w, boxes)

    def _finish(self, loss: torch.Tensor, s: torch.Tensor, seen: torch.Tensor, batch: EpisodeBatch,
                lookup: FeatureLookup, td: torch.Tensor, q_taken: torch.Tensor | None, w: torch.Tensor | None,
                boxes: torch.Tensor) -> tuple[float, torch.Tensor]:
        """The auxiliary losses on the state, the optimizer step and the diagnostics, after either
        loss. ``s`` and ``boxes`` hold the seen rows in ``seen.nonzero()`` order, as the lookup's rows."""
        if self.aux_recognition is not None or self.stop_probe is not None:
            recognized = lookup.recognized_rows(batch.scene, batch.views, seen)
            if self.aux_recognition is not None:
                loss = loss + self.aux_recognition.weight * self.aux_recognition.loss(s, recognized)
            if self.stop_probe is not None and self.pays is not None:  # "pays": where the gate would close
                vis = box_visible(boxes)
                if bool(vis.any()):
                    labels = self.pays.episodes(batch.scene, batch.views)[seen][vis]
                    if self.net.rule_ensemble:  # each member on its resample of the contexts
                        rows = batch.scene[:, None].expand_as(seen)[seen][vis]
                        gain, weight = self.pays.gains(batch.scene, batch.views)[seen][vis], self.pays.weights(rows)
                        self.stop_probe.update(s[vis], labels, gain=gain, weight=weight)
                    else:
                        self.stop_probe.update(s[vis], labels)
            elif self.stop_probe is not None:
                self.stop_probe.update(s, recognized)
        norm = self.step(loss)
        self.updates += 1
        self._last = (td, q_taken, w, norm)
        return float(loss.detach()), td

    def step(self, loss: torch.Tensor) -> torch.Tensor | None:
        """One optimizer step on ``loss``: ``zero_grad``, ``backward``, ``clip_grad_norm_`` to
        ``grad_clip``, ``step``, with the same arithmetic and less overhead. Returns the
        gradients' norm before clipping (None without clipping)."""
        params = self._params
        for p in params:  # Adam.zero_grad(set_to_none=True) without its profiler hooks: 0.1 ms
            p.grad = None
        loss.backward()
        norm = None
        if self.grad_clip > 0:  # clip_grad_norm_, in its two halves
            # get_total_norm's own sum (per-tensor norms, then the norm of those) without its
            # grouping by device and dtype, which one device and dtype make a no-op
            grads = [p.grad for p in params if p.grad is not None]
            norm = torch.linalg.vector_norm(torch.stack(torch._foreach_norm(grads)))
            # its multiply by min(1, clip / (norm + 1e-6)), computed in float32, changes no bit
            # when that factor is 1: skipped where reading the norm costs no device sync (CPU)
            # and the factor is at least 1.001 (far from float32 rounding); a NaN norm skips
            # as the factor's own test did. ~0.4 ms of a paper-sized update
            if norm.device.type != "cpu" or (float(norm) + 1e-6) * 1.001 > self.grad_clip:
                torch.nn.utils.clip_grads_with_norm_(params, self.grad_clip, norm, foreach=True)
        self.optimizer.step()
        return norm

    @property
    def stats(self) -> dict[str, float]:
        """The last update's diagnostics, reduced when read (not on every update): ``td_error``
        (mean |TD error|), ``mean_q`` (Q of the taken actions) and, where grad_clip > 0 (which
        computes it anyway), ``grad_norm`` before clipping."""
        if not self._last:
            return {}
        td, q_taken, w, norm = self._last
        out = {"td_error": float(td.mean())}  # (the cross-entropy, in an imitating update)
        if q_taken is not None:
            out["mean_q"] = float((q_taken * w).sum() / w.sum().clamp_min(1.0))
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
    # o_t is read where decision t happened or decision t - 1 happened without ending the
    # episode (o_0 always, as an empty episode's prefix); valid is a prefix of each row
    bootstraps = batch.valid & ~batch.done  # (B, T): decision t reads o_{t+1}
    return F.pad(batch.valid, (0, 1)) | F.pad(bootstraps, (1, 0), value=True)


def episode_q(net: QNetwork, feats: torch.Tensor, boxes: torch.Tensor, seen: torch.Tensor,
              *, skip_first: bool = False, with_state: bool = False) -> Any:
    """Q-values (B, T+1, n) per branch of padded episodes, computed only where ``seen``
    (B, T+1) (zeros elsewhere). ``feats`` (N, D) / ``boxes`` (N, 4; 7 with the pose) hold the seen rows in
    ``seen.nonzero()`` order. A memoryless estimator reads just those rows (and, with
    ``skip_first``, not o_0); a recurrent one is unrolled from the episode start, over
    packed sequences when it offers ``forward_packed`` (else over the padded batch). With
    ``with_state``, also the states s_t of the rows the head read."""
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
        pb = boxes.new_zeros(b, t1, boxes.shape[-1])
        pf[seen], pb[seen] = feats, boxes
        s = est(pf, pb)[seen]
    out = []
    for q in net.head(s):
        full = q.new_zeros(b, t1, q.shape[-1])
        full[rows] = q
        out.append(full)
    return (tuple(out), s) if with_state else tuple(out)
