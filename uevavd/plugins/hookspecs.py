"""Hook specifications: the contract between uevavd and its plugins.

Every hook receives one argument, ``registry``, a :class:`~uevavd.plugins.registry.KindRegistry`
bound to one component kind and to the calling plugin. Call ``registry.add(name, target,
summary=...)`` once per component, where ``target`` is a ``"module:attr"`` string naming a
keyword-only builder; the module is imported only when the component is built. Names are
global per kind: registering a name twice (by any two plugins) is an error naming both.

Hooks are called once, lazily, the first time a registry is needed.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from . import hookspec

if TYPE_CHECKING:  # pragma: no cover
    from .registry import KindRegistry


@hookspec
def register_segmenters(registry: KindRegistry) -> None:
    """Register segmenters (kind ``"segmenter"``).

    A builder returns an object satisfying :class:`uevavd.perception.base.Segmenter`: given
    RGB images (N, H, W, 3) uint8 and target boxes (N, 4) XYXY pixels, it returns the
    target mask and the masks of the surrounding objects. Example::

        registry.add("sam", "uevavd.perception.sam:build_sam_segmenter",
                     summary="Segment Anything, box + ring prompts")
    """


@hookspec
def register_encoders(registry: KindRegistry) -> None:
    """Register image encoders (kind ``"encoder"``).

    A builder returns a :class:`uevavd.perception.base.Encoder`: images (N, H, W, 3) uint8
    RGB -> features (N, D) float32. Example::

        registry.add("resnet50", "uevavd.perception.encoders:build_resnet50",
                     summary="torchvision ResNet50, pooled 2048-d")
    """


@hookspec
def register_classifiers(registry: KindRegistry) -> None:
    """Register recognition classifiers (kind ``"classifier"``).

    A builder returns a :class:`uevavd.perception.base.Classifier`: images (N, H, W, 3)
    uint8 RGB -> class probabilities (N, 5) float32 over ``uevavd.data.splits.TARGETS``.
    """


@hookspec
def register_state_estimators(registry: KindRegistry) -> None:
    """Register state estimators (kind ``"state"``).

    A builder is called with keyword ``feature_dim`` (D, the table's feature size: the
    trainer passes it) beside the method file's keys (the presets set ``input_dim`` and
    ``state_dim``: accept them, or refuse them by name), and returns a ``torch.nn.Module``
    following :class:`uevavd.state.base.StateEstimator`: ``forward(features (B, T, D), boxes
    (B, T, 4)) -> s_t (B, T, state_dim)``, causal (position t reads no later position);
    ``initial_hidden(n, device)`` the (n, H) memory on ``device`` at an episode start and
    ``step(features (N, D), boxes (N, 4), hidden (N, H)) -> (s_t, new hidden)``, with attributes ``feature_dim``,
    ``state_dim`` and ``recurrent``. The memory is one 2-D tensor; training and evaluation
    start each episode from ``initial_hidden``'s zeros (a memory whose start is learned is
    not honoured). Example::

        registry.add("gru", "uevavd.state.gru:build_gru", summary="GRU over the episode")
    """


@hookspec
def register_heads(registry: KindRegistry) -> None:
    """Register Q-value heads (kind ``"head"``).

    A builder is called with keywords ``state_dim``, ``n_types`` (7) and ``n_ranges`` (A)
    beside the method file's keys, and returns a ``torch.nn.Module`` mapping states
    (..., state_dim) to Q-values over the action space, see :mod:`uevavd.policy.heads`.
    """


@hookspec
def register_methods(registry: KindRegistry) -> None:
    """Register AOD methods (kind ``"method"``): TOML method configs.

    ``target`` is ``"package:relative/path.toml"`` (a file inside an importable package)
    or an absolute path. Example::

        registry.add("my_map", "my_pkg:methods/my_map.toml", summary="MAP with a ViT")
    """


@hookspec
def register_baselines(registry: KindRegistry) -> None:
    """Register baseline policies (kind ``"baseline"``): reference policies every evaluation
    and ablation shows beside the learned methods, and which the report and the claims
    never count as learned.

    A builder takes keyword arguments ``table`` (the ObservationTable: the recognizer's
    probabilities per view are ``table.probs`` (S, 605, 5), the features ``table.features``),
    ``config`` (the run's EnvConfig) and ``seed`` and returns a policy under the protocol of
    :mod:`uevavd.env.evaluate` (``reset(n)``, ``act(obs)``), or None where it does not
    apply (the visibility oracle on a table without visible fractions). Tag it
    ``"seeded"`` when it differs per seed: ablations then run it once per RL seed. Example::

        registry.add("random", "uevavd.env.baselines:build_random", summary="uniform over allowed actions",
                     tags=("seeded",))
    """
