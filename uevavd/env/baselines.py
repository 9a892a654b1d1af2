"""Baseline policies under the evaluation protocol of :mod:`uevavd.env.evaluate`.

Each implements ``reset(n)`` / ``act(obs) -> (a_type (n,), a_range (n,))`` and reads no
features (``needs_features = False``).
"""

from __future__ import annotations

import json
from typing import Any

import numpy as np
import torch

from ..data.grid import ACTION_TYPES, N_VIEWS, STEP_M, STOP, view_coords
from ..plugins.manager import manager
from ..table import TableError
from ..toy import toy_table
from .config import make_config
from .evaluate import evaluate_gated, evaluate_policy, stopping_summary
from .gate import box_visible, fit_to_mask
from .oracle import OraclePolicy
from .rule_values import DepartureCeilingPolicy
from .visibility_oracle import VisibilityOraclePolicy


class RandomPolicy:
    """Uniform over the *distinct allowed* actions of the current view.

    Allowed = the observation's ``mask`` (moves that are not clamped) plus stop, which
    counts once (not once per range: stop ignores its range). With ``masked=False`` it is
    uniform over the distinct actions of the whole space: 6 * A moves + stop.
    """

    needs_features = False

    def __init__(self, seed: int = 0, *, masked: bool = True) -> None:
        self.seed = int(seed)
        self.masked = masked
        self._gen: torch.Generator | None = None

    def reset(self, n: int) -> None:
        """Nothing to clear: the random stream runs on across episodes."""
        # the stream is seeded once, on the first act (on the observations' device), and runs on
        # across episodes: a caller resetting it per episode (a dataset's collector) gets other
        # actions in each, not the first episode's again

    def act(self, obs: dict[str, torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
        """A uniformly random allowed action per episode (stop counted once, whatever its range)."""
        mask = obs["mask"]  # (n, 7, A) bool
        if self._gen is None or self._gen.device != mask.device:
            self._gen = torch.Generator(device=mask.device)
            self._gen.manual_seed(self.seed)
        w = mask.float() if self.masked else torch.ones_like(mask, dtype=torch.float32)
        w[:, STOP, :] = 0.0
        w[:, STOP, 0] = 1.0
        a = w.shape[2]
        flat = torch.multinomial(w.reshape(len(w), -1), 1, generator=self._gen)[:, 0]
        return flat // a, flat % a


class PassivePolicy:
    """Stop at once: classify the first view (no flight)."""

    needs_features = False

    def reset(self, n: int) -> None:
        """Nothing to clear."""

    def act(self, obs: dict[str, torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
        """Stop, everywhere."""
        n = obs["view"].shape[0]
        dev = obs["view"].device
        return torch.full((n,), STOP, dtype=torch.int64, device=dev), torch.zeros(n, dtype=torch.int64, device=dev)


class BoxGatePolicy:
    """Scripted, from the observation alone: stop where the observed target box is non-empty
    (:func:`uevavd.env.gate.box_visible`), else the fixed move ``(a_type, a_range)``. Where that
    move would be clamped at the grid's edge it flies the longest allowed range of its type
    below the requested one, and where no range of that type is allowed it stops."""

    needs_features = False

    def __init__(self, a_type: int, a_range: int) -> None:
        if not (0 <= a_type < STOP) or a_range < 0:  # the move types are 0..STOP - 1
            raise ValueError(f"box_gate: ({a_type}, {a_range}) is not a move (type 0..{STOP - 1}, range index >= 0)")
        self.a_type, self.a_range = int(a_type), int(a_range)

    def reset(self, n: int) -> None:
        """Nothing to clear: the rule reads only the current observation."""

    def act(self, obs: dict[str, torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
        """Stop where the target's box is in view, else the fixed move, fitted to the mask (the
        longest allowed range of its type, or stop where none is allowed)."""
        mask = obs["mask"]
        n = mask.shape[0]
        a_type, a_range = fit_to_mask(mask, torch.full((n,), self.a_type, device=mask.device),
                                      torch.full((n,), self.a_range, device=mask.device))
        hidden = ~box_visible(obs["box"])
        return torch.where(hidden, a_type, STOP), torch.where(hidden, a_range, 0)


def chosen_on_train(kind: str, table, config, candidates: list, build) -> tuple[Any, dict[Any, float]]:
    """A scripted baseline's one choice, made on the table's training contexts alone (the
    ``train`` split under ``config``, so ``env.train_per_block`` and a held-out validation split
    are respected; never a test split): each candidate's policy (``build(candidate)``) evaluated
    from every start view, the highest mean return wins, ties (equal to 12 decimals) to the
    earliest candidate. Once per baseline ``kind``, table and config. Returns ``(best,
    {candidate: return})``; a table without training contexts raises
    :class:`uevavd.table.TableError`."""
    cfg = make_config(config)
    key = (kind, table.key, json.dumps(cfg.to_dict(), sort_keys=True))
    if key not in _CHOSEN:
        returns = {c: float(evaluate_policy(table, "train", build(c), cfg).ret.mean()) for c in candidates}
        order = {c: i for i, c in enumerate(candidates)}
        _CHOSEN[key] = (max(returns, key=lambda c: (round(returns[c], 12), -order[c])), returns)
    return _CHOSEN[key]


_CHOSEN: dict[tuple[str, str, str], tuple[Any, dict[Any, float]]] = {}


def box_gate_move(table, config) -> tuple[int, int, dict[tuple[int, int], float]]:
    """The box gate's fixed move (:func:`chosen_on_train`): every move type x range; ties go to
    the lowest type index, then the lowest range. Returns ``(type, range, {move: return})``."""
    a = make_config(config).max_range
    moves = [(t, r) for t in range(STOP) for r in range(a)]  # 6 x A evaluations, once per table and config
    (a_type, a_range), returns = chosen_on_train("box_gate", table, config, moves, lambda m: BoxGatePolicy(*m))
    return a_type, a_range, returns


_LEFT, _RIGHT = ACTION_TYPES.index("left"), ACTION_TYPES.index("right")  # -x, +x
_FORWARD, _BACKWARD = ACTION_TYPES.index("forward"), ACTION_TYPES.index("backward")  # +y, -y


class PoseSeekPolicy:
    """Scripted, from the observed box and the viewpoint's pose relative to the target (which the
    task gives; read from the view index, so it runs under every env config). The rule, fixed
    before any run:

    * the observed box is non-empty: stop;
    * the drone is above the target's column (x = y = 0): stop;
    * else fly horizontally toward that column along the axis with the larger offset (x on a tie),
      ``min(offset / 10 m, A)`` grid steps: never past the column, so never clamped at the grid's
      edge (a move toward the column stays on the grid); the altitude is kept;
    * after ``moves`` moves: stop.

    ``moves`` (1..T_max) is its one choice, made on the training contexts
    (:func:`pose_seek_moves`)."""

    needs_features = False

    def __init__(self, moves: int, max_range: int) -> None:
        if isinstance(moves, bool) or not isinstance(moves, int) or moves < 1 or max_range < 1:
            raise ValueError(f"pose_seek: moves={moves!r}, max_range={max_range!r}: expected integers >= 1")
        self.moves, self.max_range = moves, int(max_range)

    def reset(self, n: int) -> None:
        """Nothing to clear: the rule reads only the current observation."""

    def act(self, obs: dict[str, torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
        """The rule of the class docstring, one action per episode: stop, or the horizontal move
        toward the target's column."""
        a_type, a_range = pose_seek_hidden(obs["view"], obs["t"], self.moves, self.max_range)
        vis = box_visible(obs["box"])
        return torch.where(vis, STOP, a_type), torch.where(vis, 0, a_range)


def pose_seek_hidden(view: torch.Tensor, t: torch.Tensor, moves: int | torch.Tensor,
                     max_range: int) -> tuple[torch.Tensor, torch.Tensor]:
    """:class:`PoseSeekPolicy`'s action where the box is hidden, from the views (N,) and the
    steps t (N,) (any shape, the same): the move toward the target's column, or stop (range 0)
    above the column or after ``moves`` moves. The rule gate of training reads it too
    (``train.stop_gate = "rule"``)."""
    pose = _grid_pose(view.device).index_select(0, view.reshape(-1)).reshape(*view.shape, 3)
    dx, dy = -pose[..., 0], -pose[..., 1]  # metres to the target's column
    along_x = dx.abs() >= dy.abs()
    offset = torch.where(along_x, dx, dy)
    steps = torch.round(offset.abs() / STEP_M).long().clamp(max=max_range)
    a_type = torch.where(along_x, torch.where(dx > 0, _RIGHT, _LEFT), torch.where(dy > 0, _FORWARD, _BACKWARD))
    fly = (steps > 0) & (t < moves)
    return torch.where(fly, a_type, STOP), torch.where(fly, steps - 1, 0)


_POSE: dict[str, torch.Tensor] = {}


def _grid_pose(device: torch.device) -> torch.Tensor:
    """(605, 3) float64 viewpoint coordinates in metres on ``device`` (cached)."""
    key = str(device)
    if key not in _POSE:
        _POSE[key] = torch.as_tensor(view_coords(np.arange(N_VIEWS)), dtype=torch.float64, device=device)
    return _POSE[key]


def pose_seek_moves(table, config) -> tuple[int, dict[int, float]]:
    """``pose_seek``'s number of moves (:func:`chosen_on_train`): each of 1..T_max; ties go to
    the fewest. Returns ``(moves, {moves: return})``."""
    cfg = make_config(config)
    return chosen_on_train("pose_seek", table, cfg, list(range(1, cfg.t_max + 1)),
                           lambda k: PoseSeekPolicy(k, cfg.max_range))


def build_random(*, table=None, config=None, seed: int = 0) -> RandomPolicy:
    return RandomPolicy(seed)


def build_passive(*, table=None, config=None, seed: int = 0) -> PassivePolicy:
    return PassivePolicy()


def build_box_gate(*, table, config, seed: int = 0) -> BoxGatePolicy | None:
    """The scripted box gate with its move chosen on ``table``'s training contexts
    (:func:`box_gate_move`), or None for a table without training contexts."""
    try:
        a_type, a_range, _ = box_gate_move(table, config)
    except TableError:
        return None
    return BoxGatePolicy(a_type, a_range)


def build_pose_seek(*, table, config, seed: int = 0) -> PoseSeekPolicy | None:
    """The scripted pose rule with its number of moves chosen on ``table``'s training contexts
    (:func:`pose_seek_moves`), or None for a table without training contexts."""
    try:
        moves, _ = pose_seek_moves(table, config)
    except TableError:
        return None
    return PoseSeekPolicy(moves, make_config(config).max_range)


def build_departure_ceiling(*, table, config, seed: int = 0, departures: int = 1):
    """``pose_seek`` (its moves chosen on the training contexts) departed from at most
    ``departures`` times with each context's exact values: the privileged ceiling of a method
    anchored to the rule (:class:`~uevavd.env.rule_values.DepartureCeilingPolicy`), or None
    where ``pose_seek`` does not apply."""
    rule = build_pose_seek(table=table, config=config)
    return None if rule is None else DepartureCeilingPolicy(table, config, rule, departures)


def build_departure_ceiling2(*, table, config, seed: int = 0):
    """:func:`build_departure_ceiling` with two departures."""
    return build_departure_ceiling(table=table, config=config, departures=2)


def build_visibility_oracle(*, table, config, seed: int = 0):
    """The visibility oracle, or None for a table without visible fractions."""
    import numpy as np

    if np.isnan(np.asarray(table.visible)).all():
        return None

    return VisibilityOraclePolicy(table, config)


def build_oracle(*, table, config, seed: int = 0):
    return OraclePolicy(table, config)


def baseline_entries() -> list:
    """The registered baselines (:func:`uevavd.plugins.hookspecs.register_baselines`), in
    registration order."""
    return manager.registry.in_order("baseline")


class BaselineError(ValueError):
    """A plugin's baseline fails before any evaluation uses it (one line: which, where, why)."""


_CHECKED: set[str] = set()


def check_baselines() -> None:
    """Every baseline a third-party plugin registers, built (seed 0) and evaluated on a toy
    table's hard split, once per process: a broken one is a :class:`BaselineError` naming the
    baseline and its plugin before ``evaluate`` or ``ablate`` writes anything (it failed every
    evaluation, in ``ablate`` after training every run, naming neither). The built-in ones are
    the suite's to check."""
    table = config = None
    for entry in baseline_entries():
        key = f"{entry.name}|{entry.target}"
        if entry.plugin.startswith("uevavd.") or key in _CHECKED:
            continue
        if table is None:
            table, config = toy_table(n_train=1, n_hard=1, feature_dim=8), make_config(None)
        try:
            policy = entry.load()(table=table, config=config, seed=0)
            if policy is not None and not np.isfinite(evaluate_policy(table, "hard", policy, config).ret).all():
                raise ValueError("non-finite returns")
        except Exception as exc:  # noqa: BLE001 - whatever the plugin's code raises, in one line
            raise BaselineError(f"baseline {entry.name!r} ({entry.target}, plugin {entry.plugin!r}) fails on a toy "
                                f"table: {type(exc).__name__}: {' '.join(str(exc).split())}; fix the plugin, or block "
                                f"it with UEVAVD_DISABLED_PLUGINS={entry.plugin}") from None
        _CHECKED.add(key)


def baseline_names() -> tuple[str, ...]:
    """Names of the registered baselines: the policies the report and the claims never
    count as learned."""
    return tuple(e.name for e in baseline_entries())


def reference_policies(table, config, *, seed: int = 0) -> dict:
    """The baselines every evaluation shows beside a learned policy, by name, in
    registration order (built in: random (``seed``), passive, the visibility oracle where
    the table knows visible fractions, and the class-knowing oracle, an upper bound)."""
    out = {}
    for entry in baseline_entries():
        policy = entry.load()(table=table, config=config, seed=seed)
        if policy is not None:
            out[entry.name] = policy
    return out


def evaluate_with_baselines(table, split: str, policy, name: str, config, *, device="cpu", baselines: bool = True,
                            contexts=None) -> dict:
    """``{policy name: (EvalResult, gated EvalResult or None)}``: ``policy`` as ``name``,
    evaluated exhaustively on ``split`` (optionally only ``contexts``) under ``config`` and
    again behind the stop gate (:func:`~uevavd.env.evaluate.evaluate_gated`), then each of
    :func:`reference_policies` when ``baselines`` (not gated: they are the references)."""
    if baselines:
        check_baselines()
    out = {name: evaluate_gated(table, split, policy, config, device=device, contexts=contexts)}
    for n, p in (reference_policies(table, config) if baselines else {}).items():
        out[n] = (evaluate_policy(table, split, p, config, device=device, contexts=contexts), None)
    return out


def summary_row(res, gated) -> dict:
    """An evaluation's summary with ``gated_return`` (NaN where it was not gated)."""
    return stopping_summary(res, gated) if gated is not None else {**res.summary(), "gated_return": float("nan")}


def evaluate_beside_baselines(table, split: str, policy, name: str, config, *, device="cpu", baselines: bool = True,
                              contexts=None):
    """``(DataFrame, per-context DataFrame)``: one row per policy of
    :func:`evaluate_with_baselines`, with :meth:`~uevavd.env.evaluate.EvalResult.summary`'s
    columns (the stopping diagnosis among them) and ``gated_return``; and ``policy``'s rows
    per context, with its gated return. What ``uevavd evaluate``, ``Run.evaluate`` and the
    model zoo print."""
    import pandas as pd

    results = evaluate_with_baselines(table, split, policy, name, config, device=device, baselines=baselines,
                                      contexts=contexts)
    frame = pd.DataFrame([{"policy": n, **summary_row(*r)} for n, r in results.items()]).set_index("policy")
    res, gated = results[name]
    per_context = res.per_context()
    per_context["gated_return"] = gated.per_context()["mean_return"].to_numpy()
    return frame, per_context
