"""Procedural scene generation: one :class:`Scene` per (seed, context id).

The target stands at the origin heading +y (the same orientation in every context), parked
on a street next to buildings and street trees (urban), or in a clearing of a wood beside a
dirt track, facing across it (woodland). Training and simple-test contexts are urban with
the training placement; the hard test set holds both terrains, as the paper's Table 1 says:
urban contexts whose placement and surroundings are drawn from ranges outside the training
ones (``placement = "shifted"``), and woodland contexts (:func:`terrain_of`).

Every context of every split obeys one validity rule (:data:`VALIDITY`, checked by
:func:`context_draw`): a draw that breaks it is replaced by the next draw of the same
context, deterministically. Draw 0 comes from ``numpy.random.default_rng([seed,
context_id])``, draw k > 0 from ``default_rng([seed, context_id, k])``; the same inputs give
the same scene.
"""

from __future__ import annotations

import dataclasses
import functools
import json
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from ..grid import N_VIEWS
from ..splits import BLOCK, TARGETS, block_of, check_context, scene_name, split_of
from .geometry import Primitives
from .ground import Strip
from .scenes import TARGET_ID, TARGET_YAW, InstanceIds, Scene, build_scene, finish_scene
from .vehicles import MODELS, add_vehicle, vehicle_height, vehicle_length

#: Target of block k in the synthetic world (the paper's table order).
BLOCK_TARGETS: tuple[str, ...] = ("hatchback", "pickup", "sportscar", "sedan", "suv")
#: ``train_605`` is rendered in this many context-like stages per target (each viewpoint in
#: one of them, see :func:`training_stages`), so that the classifier's crops see the
#: backgrounds, light and shadows of the contexts; every ``WOODLAND_EVERY``-th stage is woodland.
TRAIN_STAGES = 60
WOODLAND_EVERY = 5
@dataclass(frozen=True)
class ValidityRule:
    """The rule every context of every split obeys: at least ``min_clear_share`` of its 605
    views show the target with visible fraction >= ``clear_at``, and at least ``min_full``
    views show it whole (visible >= ``full_at``). It is checked on the views rendered at
    ``check_size`` px, so that the chosen draw does not depend on the crop size a world is
    written at; ``margin`` is added to ``min_clear_share`` there because the visible fraction
    moves by up to 0.7 points between 48 and 256 px (docs/synthetic_world.md), so the rule
    holds at every written size."""

    clear_at: float = 0.9
    min_clear_share: float = 0.10
    full_at: float = 0.99
    min_full: int = 1
    check_size: int = 48
    margin: float = 0.02
    max_draws: int = 64

    def passes(self, visible: np.ndarray, *, margin: float = 0.0) -> bool:
        """True when (605,) visible fractions satisfy the rule (with an extra ``margin``)."""
        v = np.asarray(visible, np.float64)
        return bool(np.mean(v >= self.clear_at) >= self.min_clear_share + margin
                    and int(np.sum(v >= self.full_at)) >= self.min_full)

    def describe(self) -> str:
        return (f">= {self.min_clear_share:.0%} of views with visible >= {self.clear_at} and >= {self.min_full} "
                f"view(s) with visible >= {self.full_at}")


#: Fixed before any learning run (see docs/synthetic_world.md); never tuned to results.
VALIDITY = ValidityRule()

#: Generator version: bump it whenever the world or the renderer changes what they write,
#: so that resumed or cached worlds written by an older generator are redone.
#: 4: the hard split holds shifted-urban and woodland contexts; the validity rule.
#: 5: hulls (buildings, vehicles, trunks) cast shadows too (version 4's shadow map let every
#: sun ray miss them; docs/synthetic_world.md, "Shadows").
VERSION = 5

#: The first valid draw of every context for the presets' world seed, recorded so that writing
#: a preset's world does not repeat the validity search (a fifth of its time). Written by
#: ``python -m uevavd.data.synthetic.draws``; read only when it was made by this generator
#: version under this validity rule (tests recompute entries); other seeds search.
DRAWS_FILE = Path(__file__).with_name("draws.json")


def target_of(context_id: int) -> str:
    """The synthetic world's target in a context's block."""
    return BLOCK_TARGETS[block_of(context_id)]


def terrain_of(context_id: int) -> tuple[str, str]:
    """``(terrain, placement)`` of a context. Training and simple-test contexts: urban with
    the training placement. Hard-test contexts (5 per block, positions j = 0..4): woodland
    where ``(j + block) % 2 == 1``, else urban with the shifted placement, so that the
    paper's 25 hard contexts hold 12 woodland and 13 shifted-urban ones, every target meets
    both terrains, and a world with one hard context per block (the quick preset) holds
    both too (blocks 0, 2, 4 urban; 1, 3 woodland)."""
    cid = check_context(context_id)
    if split_of(cid) != "hard":
        return "urban", "training"
    j = (cid - 1) % BLOCK - 25
    return ("woodland", "training") if (j + block_of(cid)) % 2 == 1 else ("urban", "shifted")


def draw_context(context_id: int, *, seed: int, draw: int, target: str | None = None) -> Scene:
    """Draw number ``draw`` of a context's scene, valid or not (:func:`build_context` gives
    the first valid one)."""
    cid = check_context(context_id)
    terrain, placement = terrain_of(cid)
    rng = np.random.default_rng([int(seed), cid] if draw == 0 else [int(seed), cid, int(draw)])
    scene = build_scene(scene_name(cid), cid, split_of(cid), terrain, target or target_of(cid), rng,
                   placement=placement)
    return replace(scene, draw=int(draw))


def draws_record() -> dict:
    """What :data:`DRAWS_FILE` must say about its making to be used."""
    return {"version": VERSION, "rule": dataclasses.asdict(VALIDITY)}


@functools.lru_cache(maxsize=1)
def recorded_draws() -> dict[tuple[int, int], int]:
    """``{(seed, context): draw}`` from :data:`DRAWS_FILE`, empty when it is missing or was
    made by another generator version or validity rule."""
    try:
        data = json.loads(DRAWS_FILE.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return {}
    if {k: data.get(k) for k in ("version", "rule")} != draws_record():
        return {}
    return {(int(s), int(c)): int(d) for s, by_context in data["draws"].items() for c, d in by_context.items()}


@functools.lru_cache(maxsize=512)
def context_draw(context_id: int, *, seed: int) -> int:
    """The first draw of a context that passes :data:`VALIDITY` at its check size (with the
    block's own target): recorded in :data:`DRAWS_FILE` for the presets' seed, else
    :func:`search_draw`; cached per process."""
    recorded = recorded_draws().get((int(seed), int(context_id)))
    return recorded if recorded is not None else search_draw(context_id, seed=seed)


def validity_views(scene: Scene) -> np.ndarray:
    """(605,) the visible fractions :data:`VALIDITY` reads: the scene's views rendered at its
    check size, without shading (the colours do not change what is seen)."""
    from .render import render_views

    return render_views(scene, VALIDITY.check_size, shade=False).visible


def search_draw(context_id: int, *, seed: int) -> int:
    """The validity search: draws 0, 1, ... of the context until one passes, rendering its
    605 views at the check size (:func:`validity_views`) per draw tried."""
    for draw in range(VALIDITY.max_draws):
        if VALIDITY.passes(validity_views(draw_context(context_id, seed=seed, draw=draw)), margin=VALIDITY.margin):
            return draw
    raise RuntimeError(f"context {context_id} (seed {seed}): no draw among {VALIDITY.max_draws} passes the "
                       f"validity rule ({VALIDITY.describe()}); the generator's ranges are broken")


def build_context(context_id: int, *, seed: int, target: str | None = None) -> Scene:
    """The scene of context ``context_id`` (1..150) for a world seed: its first draw that
    passes the validity rule. ``target`` overrides the block's target (tests use this to
    place another model in the same context; the draw is the one chosen for the block's
    target)."""
    cid = check_context(context_id)
    return draw_context(cid, seed=seed, draw=context_draw(cid, seed=int(seed)), target=target)


def training_stage_terrain(stage: int) -> str:
    """Terrain of ``train_605`` stage ``stage``: every ``WOODLAND_EVERY``-th stage is woodland."""
    return "woodland" if stage % WOODLAND_EVERY == WOODLAND_EVERY - 1 else "urban"


def training_stages(seed: int) -> np.ndarray:
    """(605,) int: the ``train_605`` stage (0..TRAIN_STAGES-1) each viewpoint is rendered in.
    A seeded permutation dealt round-robin, so every stage's views spread over the grid; the
    same assignment for every target (held-out viewpoints meet every stage)."""
    perm = np.random.default_rng([int(seed), 7605]).permutation(N_VIEWS)
    stages = np.empty(N_VIEWS, np.int64)
    stages[perm] = np.arange(N_VIEWS) % TRAIN_STAGES
    return stages


def build_training_stage(target: str, *, seed: int, stage: int) -> Scene:
    """Stage ``stage`` of the scene ``train_605`` with ``target`` at the origin: a context-like
    scene (buildings, trees, parked cars, its own sun and ground) drawn from
    ``default_rng([seed, 605, stage])``, independent of every context and the same for the
    five targets (only the target differs), so that the background says nothing about the
    class. Views are rendered from it without the objects that hide the target in that view
    (:func:`render.render_unoccluded_view`)."""
    if target not in TARGETS:
        raise ValueError(f"unknown target {target!r}: expected one of {list(TARGETS)}")
    if not 0 <= stage < TRAIN_STAGES:
        raise ValueError(f"stage={stage}: expected 0..{TRAIN_STAGES - 1}")
    rng = np.random.default_rng([int(seed), 605, int(stage)])
    longest = max(vehicle_length(m) for m in MODELS) / 2  # parked cars clear of any of the five
    scene = build_scene("train_605", None, "train_605", training_stage_terrain(stage), BLOCK_TARGETS[0], rng, longest)
    return with_target(scene, target)


def with_target(scene: Scene, target: str) -> Scene:
    """The same scene with model ``target`` in place of its target (same id, pose and paint)."""
    if target not in TARGETS:
        raise ValueError(f"unknown target {target!r}: expected one of {list(TARGETS)}")
    new = Primitives()
    add_vehicle(new, target, centre=(0.0, 0.0), yaw=TARGET_YAW, instance=TARGET_ID)
    fresh = new.arrays()
    keep = scene.prims["h_inst"] != TARGET_ID
    prims = {k: (np.concatenate([fresh[k], v[keep]]) if k.startswith("h_") else v) for k, v in scene.prims.items()}
    return replace(scene, target=target, prims=prims, look_at=np.array([0.0, 0.0, vehicle_height(target) / 2]))


def build_unoccluded(target: str, *, seed: int, scene: str = "00") -> Scene:
    """An open scene (street, pavement and grass, nothing standing) with one target: the
    scenes "00" and "train_605". The ground and light depend on (seed, scene) only."""
    if target not in TARGETS:
        raise ValueError(f"unknown target {target!r}: expected one of {list(TARGETS)}")
    rng = np.random.default_rng([int(seed), 1000 + sum(map(ord, scene))])
    prims = Primitives()
    ids = InstanceIds({TARGET_ID: "target"})
    add_vehicle(prims, target, centre=(0.0, 0.0), yaw=TARGET_YAW, instance=TARGET_ID)
    road_w = rng.uniform(7.0, 11.0)
    curb = rng.uniform(1.1, 1.6)
    strips = [
        Strip("y", -curb, road_w - curb, "road"),
        Strip("y", -curb - 3.0, -curb, "pavement"),
        Strip("y", road_w - curb, road_w - curb + 3.0, "pavement"),
    ]
    return finish_scene(scene, None, scene, "urban", target, prims, ids, strips, rng, TARGET_ID + 1, (40.0, 70.0))
