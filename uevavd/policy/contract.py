"""The rules a ``state`` or ``head`` component must follow, checked before a run writes anything.

The trainer builds its network through :func:`build_checked_network`: each component is built
with the arguments the trainer passes (``feature_dim``; ``state_dim``, ``n_types``,
``n_ranges``) and run through the rules below on a few random inputs, on the CPU, with torch's
global random stream untouched and no parameter changed, so a run's numbers are the same
with the checks as without. A broken rule is a :class:`ComponentError`: one line naming the
component, where it is registered and the rule (``uevavd train`` prints it and exits 2).
:mod:`uevavd.testing` runs the same rules for plugin authors.
"""

from __future__ import annotations

import contextlib
import inspect
from collections.abc import Callable, Iterator
from typing import Any

import torch

from ..config import Component
from ..data.grid import DEFAULT_MAX_RANGE, N_TYPES, XS, YS, ZS
from ..plugins.manager import manager
from ..state.base import reads_pose
from .network import QNetwork


class ComponentError(ValueError):
    """A component broke a rule of its kind's protocol (one line: what, where, which rule)."""


def _where(component: Component | None) -> str:
    if component is None:
        return ""
    try:
        entry = manager.registry.get(component.kind, component.name)
    except ValueError:
        return f" {component.name!r}"
    origin = "built-in" if entry.plugin.startswith("uevavd.") else f"plugin {entry.plugin!r}"
    return f" {component.name!r} ({entry.target}, {origin})"


def _one_line(exc: BaseException) -> str:
    return " ".join(f"{type(exc).__name__}: {exc}".split())


@contextlib.contextmanager
def _calling(what: str, call: str) -> Iterator[None]:
    """Any error inside (a shape error, an IndexError on a mask) becomes a ComponentError."""
    try:
        yield
    except ComponentError:
        raise
    except Exception as exc:  # noqa: BLE001 - whatever a plugin raises is reported, in one line
        raise ComponentError(f"{what}: {call} raised {_one_line(exc)}") from None


def _rule(ok: bool, what: str, message: str) -> None:
    if not ok:
        raise ComponentError(f"{what}: {message}")


@contextlib.contextmanager
def _probing(module: torch.nn.Module) -> Iterator[None]:
    """No gradient, eval mode, torch's global (CPU) random stream forked: the probes change
    nothing a run's numbers depend on."""
    was_training = module.training
    with torch.random.fork_rng(devices=[]), torch.no_grad():
        module.eval()
        try:
            yield
        finally:
            module.train(was_training)


def check_estimator_rules(est: Any, *, feature_dim: int | None = None, batch: int = 3, steps: int = 4,
                          what: str = "state estimator") -> None:
    """The ``state`` protocol (:class:`uevavd.state.base.StateEstimator`): attributes, shapes
    and dtypes, causality (s_t reads no later observation), the memory at an episode start
    (a 2-D tensor of zeros, which training and evaluation restart each episode from), and
    ``step`` from that memory agreeing with ``forward``."""
    _rule(isinstance(est, torch.nn.Module), what, f"the builder returned {type(est).__name__}; expected a torch.nn.Module")
    for attr in ("feature_dim", "state_dim", "recurrent"):
        _rule(hasattr(est, attr), what, f"has no attribute {attr!r} (feature_dim, state_dim and recurrent are required)")
    d, k = int(est.feature_dim), int(est.state_dim)
    if feature_dim is not None:
        _rule(d == feature_dim, what, f"feature_dim is {d} but it was built for the table's {feature_dim}; "
              "set self.feature_dim from the builder's feature_dim argument")
    g = torch.Generator().manual_seed(0)
    f = torch.randn(batch, steps, d, generator=g)
    b = torch.rand(batch, steps, 4, generator=g)
    if reads_pose(est):  # the box, then the pose in metres on the grid (uevavd.state.base.estimator_boxes)
        low, high = torch.tensor([XS[0], YS[0], ZS[0]]), torch.tensor([XS[-1], YS[-1], ZS[-1]])
        b = torch.cat([b, low + (high - low) * torch.rand(batch, steps, 3, generator=g)], dim=-1)
    w = b.shape[-1]
    call = f"forward(features ({batch}, {steps}, {d}) float32, boxes ({batch}, {steps}, {w}) float32)"
    with _probing(est):
        with _calling(what, call):
            s = est(f, b)
        _rule(isinstance(s, torch.Tensor), what, f"{call} returned {type(s).__name__}; expected a tensor "
              f"(B, T, state_dim)")
        _rule(tuple(s.shape) == (batch, steps, k), what,
              f"{call} returned shape {tuple(s.shape)}; expected (B, T, state_dim) = {(batch, steps, k)}")
        _rule(s.dtype == torch.float32, what, f"{call} returned {s.dtype}; expected float32")
        f2, b2 = f.clone(), b.clone()
        f2[:, -1] += 5.0
        b2[:, -1] = 1.0 - b2[:, -1]
        with _calling(what, call):
            s2 = est(f2, b2)
        _rule(torch.allclose(s[:, :-1], s2[:, :-1], atol=1e-5), what,
              "not causal: s_t changed when a later observation changed (position t may read positions <= t only; "
              "replayed episodes are padded after their end)")
        with _calling(what, f"initial_hidden({batch}, device)"):  # as the trainer and the evaluation call it
            h = est.initial_hidden(batch, torch.device("cpu"))
        _rule(isinstance(h, torch.Tensor) and h.dim() == 2 and h.shape[0] == batch and h.dtype == torch.float32,
              what, f"initial_hidden({batch}) returned "
              f"{tuple(h.shape) if isinstance(h, torch.Tensor) else type(h).__name__}; expected one float32 "
              f"tensor (n, H) (H = 0 when not recurrent)")
        _rule(not bool(h.any()), what,
              "initial_hidden() is not zeros: training and evaluation start every episode from a zero memory "
              "(hidden * (t != 0)), so a learned initial memory would act differently than it was trained; "
              "learn it inside forward/step from a zero memory instead")
        h0 = h
        for t in range(steps):
            with _calling(what, f"step(features ({batch}, {d}), boxes ({batch}, {w}), hidden {tuple(h.shape)})"):
                out = est.step(f[:, t], b[:, t], h)
            _rule(isinstance(out, tuple) and len(out) == 2, what, "step() must return (s_t (N, state_dim), new hidden (N, H))")
            st, h2 = out
            _rule(isinstance(h2, torch.Tensor) and tuple(h2.shape) == tuple(h.shape), what,
                  f"step() returned a memory of shape {tuple(getattr(h2, 'shape', ()))}; expected {tuple(h.shape)}, "
                  "the shape initial_hidden gives")
            _rule(isinstance(st, torch.Tensor) and torch.allclose(st, s[:, t], atol=1e-4), what,
                  f"step() at t={t} from initial_hidden() disagrees with forward() (acting and learning would "
                  "see different states)")
            h = h2
        if hasattr(est, "step_encoded"):
            _check_fast_path(est, f, b, h0, what)
        if est.recurrent:  # it reads earlier views: at least the one before (a memory, or a window of k >= 2)
            f3, b3 = f.clone(), b.clone()  # o_{t-1} whole: its features and its box (and pose)
            f3[:, -2] += 5.0
            b3[:, -2] = 1.0 - b3[:, -2]
            with _calling(what, call):
                s3 = est(f3, b3)
            _rule(not torch.allclose(s3[:, -1], s[:, -1]), what,
                  "recurrent = True but s_t reads no earlier view than o_t (it did not change with o_{t-1}): set "
                  "recurrent = False for an estimator of the current view alone (training then reads each view by "
                  "itself); a memory or a window of the last k views reads o_{t-1} and keeps recurrent = True")


def _check_fast_path(est: Any, f: torch.Tensor, b: torch.Tensor, h: torch.Tensor, what: str) -> None:
    """The optional ``step_encoded`` path the evaluation takes when an estimator offers it: each
    view projected once by ``encoder.project``, then ``encoder.combine`` with the box, then
    ``step_encoded``; it must give what ``step`` gives (a wrong one trained through ``step`` and
    was scored through itself)."""
    enc = getattr(est, "encoder", None)
    for attr in ("image_dim", "project", "combine"):
        _rule(hasattr(enc, attr), what, f"offers step_encoded but its encoder has no {attr!r}: the evaluation's fast "
              "path reads encoder.image_dim, encoder.project(features) and encoder.combine(image, boxes); give the "
              "encoder those (uevavd.state.base.ObservationEncoder has them) or drop step_encoded")
    for t in range(f.shape[1]):
        call = f"step_encoded(encoder.combine(encoder.project(features), boxes), hidden) at t={t}"
        with _calling(what, call):
            image = enc.project(f[:, t])
            _rule(tuple(image.shape) == (f.shape[0], int(enc.image_dim)), what,
                  f"encoder.project gave shape {tuple(image.shape)}; expected (N, encoder.image_dim = {enc.image_dim})")
            fast, h_fast = est.step_encoded(enc.combine(image, b[:, t]), h)
        plain, h = est.step(f[:, t], b[:, t], h)
        _rule(torch.allclose(fast, plain, atol=1e-5) and torch.allclose(h_fast, h, atol=1e-5), what,
              f"{call} disagrees with step() (the evaluation takes the fast path, training the plain one: a policy "
              "would be scored on other states than it learned); make step_encoded step() from an encoded g_t")


def check_head_rules(head: Any, *, state_dim: int, n_types: int = N_TYPES, n_ranges: int = DEFAULT_MAX_RANGE,
                     what: str = "head") -> None:
    """The ``head`` protocol (:mod:`uevavd.policy.heads`): ``forward`` gives ``n_branches``
    Q tensors, ``greedy`` keeps to the allowed actions, ``taken`` / ``bootstrap`` /
    ``weights`` have the shapes the learner reads, and a gradient reaches the state."""
    _rule(isinstance(head, torch.nn.Module), what, f"the builder returned {type(head).__name__}; expected a torch.nn.Module")
    _rule(hasattr(head, "n_branches"), what, "has no attribute 'n_branches' (how many Q tensors forward returns)")
    k = int(head.n_branches)
    g = torch.Generator().manual_seed(0)
    s = torch.randn(5, 3, state_dim, generator=g)
    mask = torch.rand(5, 3, n_types, n_ranges, generator=g) > 0.5
    mask[..., n_types - 1, :] = True  # stop is always allowed
    with _probing(head):
        with _calling(what, f"forward(s (5, 3, {state_dim}))"):
            q = head(s)
        _rule(isinstance(q, tuple) and len(q) == k, what,
              f"forward returned {type(q).__name__}; expected a tuple of n_branches = {k} tensors")
        with _calling(what, "greedy(q, mask (5, 3, 7, A))"):
            a_type, a_range = head.greedy(q, mask)
        _rule(tuple(a_type.shape) == tuple(a_range.shape) == (5, 3), what,
              f"greedy returned shapes {tuple(a_type.shape)}, {tuple(a_range.shape)}; expected (5, 3) each")
        allowed = mask.reshape(-1, n_types, n_ranges)[torch.arange(15), a_type.reshape(-1), a_range.reshape(-1)]
        _rule(bool(allowed.all()), what, "greedy chose an action the mask forbids")
        with _calling(what, "taken(q, a_type, a_range)"):
            taken = head.taken(q, a_type, a_range)
        _rule(tuple(taken.shape) == (5, 3, k), what, f"taken has shape {tuple(taken.shape)}; expected (5, 3, {k})")
        with _calling(what, "bootstrap(q_online, q_target, mask)"):
            boot = head.bootstrap(q, q, mask)
        _rule(tuple(boot.shape) == (5, 3, k), what, f"bootstrap has shape {tuple(boot.shape)}; expected (5, 3, {k})")
        with _calling(what, "weights(a_type)"):
            w = head.weights(a_type)
        _rule(tuple(w.shape) == (5, 3, k), what, f"weights has shape {tuple(w.shape)}; expected (5, 3, {k})")
    with _probing(head), torch.enable_grad():  # torch.autograd.grad fills no parameter's .grad
        s.requires_grad_(True)
        grad = torch.autograd.grad(head.taken(head(s), a_type, a_range).sum(), s, allow_unused=True)[0]
    _rule(grad is not None and bool(torch.isfinite(grad).all()) and bool(grad.any()), what,
          "no finite gradient reaches the state from the Q of the taken actions")


def _build(component: Component, what: str, runtime: dict[str, Any], hint: str) -> Any:
    try:
        return component.build(**runtime)
    except TypeError as exc:  # a builder that does not take what the trainer passes
        raise ComponentError(f"{what}: its builder, called with the method's keys and {sorted(runtime)}, raised "
                             f"{_one_line(exc)}; {hint}") from None


def build_checked_network(state: Component, head: Component, feature_dim: int, *, n_types: int = N_TYPES,
                          n_ranges: int = DEFAULT_MAX_RANGE) -> QNetwork:
    """:func:`~uevavd.policy.network.build_network`, each component checked against its rules
    (a :class:`ComponentError` names the first broken one); the same network, built from
    torch's global random stream as there."""
    state_what = f"state{_where(state)}"
    head_what = f"head{_where(head)}"
    est = _build(state, state_what, {"feature_dim": feature_dim},
                 "a state builder takes keyword feature_dim (the table's feature size) beside the method file's "
                 "keys (the presets set input_dim and state_dim)")
    # the estimator is checked before the head is built: a head's initialisation then draws
    # from the same point of the global stream as build_network's
    check_estimator_rules(est, feature_dim=feature_dim, what=state_what)
    head_kwargs: dict[str, Any] = {"n_types": n_types, "n_ranges": n_ranges}
    if "state_dim" not in head.kwargs:
        head_kwargs["state_dim"] = est.state_dim
    q_head = _build(head, head_what, head_kwargs,
                    "a head builder takes keywords state_dim, n_types and n_ranges beside the method file's keys")
    net = QNetwork(est, q_head)
    check_head_rules(q_head, state_dim=int(est.state_dim), n_types=n_types, n_ranges=n_ranges, what=head_what)
    return net


#: What each kind's builder is called with by the host, beside the method file's keys.
RUNTIME_ARGUMENTS: dict[str, tuple[str, ...]] = {
    "state": ("feature_dim",),
    "head": ("state_dim", "n_types", "n_ranges"),
    "baseline": ("table", "config", "seed"),
}


def missing_runtime_arguments(kind: str, builder: Callable[..., Any]) -> list[str]:
    """The runtime keywords of ``kind`` that ``builder`` cannot take (none with ``**kwargs``)."""
    params = inspect.signature(builder).parameters
    if any(p.kind is p.VAR_KEYWORD for p in params.values()):
        return []
    return [a for a in RUNTIME_ARGUMENTS.get(kind, ()) if a not in params]
