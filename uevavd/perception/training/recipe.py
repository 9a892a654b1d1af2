"""The recognizer's recipe (a preset's ``[classifier]`` section) as a plain dataclass, apart
from the training code: an ablation checks it before any heavy import, so that a mistake in it
(or in any argument) is refused in about a second."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from ...config_rules import did_you_mean

ARCHS = ("resnet18", "efficientnet_lite0")
#: torch CPU threads the recognizer trains on. Its float sums are split between threads and
#: round differently with another count (not with another number of cores), so the count is
#: fixed: any machine trains the model zoo's recognizer (trained on 2) weight for weight.
THREADS = 2


@dataclass
class ClassifierRecipe:
    """How the recognition classifier is trained (a preset's ``[classifier]`` section): not
    a run's ``settings.json``, nor an ablation's sweep setting."""

    arch: str = "resnet18"  #: "resnet18" (the paper's) or "efficientnet_lite0"
    init: str = "imagenet"  #: "imagenet" or "random"
    epochs: int = 12
    batch_size: int = 32
    lr: float = 3e-3
    weight_decay: float = 1e-4
    val_fraction: float = 0.15
    seed: int = 0
    shift: float = 0.06  #: max shift, fraction of the image size
    scale: float = 0.08  #: max relative zoom in or out
    jitter: float = 0.25  #: max relative change of contrast / saturation
    #: brightness factor range (the measured quick-world classifier used (0.7, 1.25), jitter 0.15)
    brightness: tuple[float, float] = (0.45, 1.25)
    max_views: int | None = None  #: use only this many viewpoints (seeded sample) for train + val

    @classmethod
    def from_preset(cls, preset: Mapping[str, Any], **fields: Any) -> ClassifierRecipe:
        """The recipe of a preset's ``[classifier]`` table (``{}``: the defaults), ``fields``
        (e.g. the recognizer ``seed``) replacing its values, checked: a key the recipe does
        not have, or a value it refuses, is a ``ValueError`` naming the preset."""
        values = {**preset.get("classifier", {}), **fields}
        where = f"preset {preset.get('name', '?')!r} [classifier]" if preset else "the recognizer's recipe"
        known = sorted(cls.__dataclass_fields__)
        unknown = sorted(set(values) - set(known))
        if unknown:
            raise ValueError(f"{where}: no key {unknown[0]!r}{did_you_mean(unknown[0], known)} (accepted keys: {known})")
        recipe = cls(**values)
        try:
            recipe.check()
        except ValueError as exc:
            raise ValueError(f"{where}: {exc}") from None
        except TypeError:  # e.g. epochs = "8"
            raise ValueError(f"{where} {values}: expected numbers where the recipe has numbers "
                             f"(defaults: {cls().__dict__})") from None
        return recipe

    def check(self) -> None:
        if self.arch not in ARCHS:
            raise ValueError(f"arch={self.arch!r}: expected one of {list(ARCHS)}")
        if self.init not in ("imagenet", "random"):
            raise ValueError(f"init={self.init!r}: expected 'imagenet' or 'random'")
        if self.epochs < 1 or self.batch_size < 1:
            raise ValueError(f"epochs={self.epochs}, batch_size={self.batch_size}: expected positive integers")
        if not 0.0 < self.val_fraction < 1.0:
            raise ValueError(f"val_fraction={self.val_fraction}: expected a share in (0, 1)")
        if self.max_views is not None and self.max_views < 2:
            raise ValueError(f"max_views={self.max_views}: expected at least 2 (or None for all)")
        if not self.lr > 0:
            raise ValueError(f"lr={self.lr}: expected > 0")
