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

from ..splits import BLOCK, TARGETS, block_of, check_context, scene_name, split_of
from .geometry import M_BARK, M_CANOPY, M_FACADE, M_FLAT, Primitives, box
from .ground import Strip, build_ground
from .vehicles import MODELS, add_vehicle, vehicle_height, vehicle_length

#: Target of block k in the synthetic world (the paper's table order).
BLOCK_TARGETS: tuple[str, ...] = ("hatchback", "pickup", "sportscar", "sedan", "suv")
TARGET_ID = 1
TARGET_YAW = np.pi / 2  # heading +y (north)
#: Sun elevation range (degrees) per terrain.
SUN_ELEVATION = {"urban": (35.0, 72.0), "woodland": (28.0, 65.0)}
#: ``train_605`` is rendered in this many context-like stages per target (each viewpoint in
#: one of them, see :func:`training_stages`), so that the classifier's crops see the
#: backgrounds, light and shadows of the contexts; every ``WOODLAND_EVERY``-th stage is woodland.
TRAIN_STAGES = 60
WOODLAND_EVERY = 5

_CAR_PAINTS = (
    (0.75, 0.12, 0.10), (0.92, 0.92, 0.90), (0.08, 0.08, 0.09), (0.15, 0.25, 0.55),
    (0.80, 0.65, 0.15), (0.30, 0.32, 0.30), (0.45, 0.08, 0.10), (0.20, 0.45, 0.30),
)


@dataclass
class Scene:
    """A renderable scene. ``prims``: arrays from :meth:`Primitives.arrays`; ground maps from
    :func:`ground.build_ground`; ``sun_dir`` (3,) unit vector towards the sun; ``sun_rgb``
    and ``ambient_rgb`` (3,) light colours; ``look_at`` (3,) the target's centre."""

    name: str
    context: int | None
    split: str
    terrain: str
    target: str
    prims: dict[str, np.ndarray]
    ground_rgb: np.ndarray
    ground_ids: np.ndarray
    categories: dict[int, str]
    sun_dir: np.ndarray
    sun_rgb: np.ndarray
    ambient_rgb: np.ndarray
    look_at: np.ndarray
    placement: str = "training"  #: "training" or "shifted" (hard-test urban contexts)
    draw: int = 0  #: which draw of the context passed the validity rule (0 = the first)


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
VERSION = 4

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


class _Ids:
    def __init__(self, categories: dict[int, str]):
        self.categories = categories
        self.next = max(categories) + 1

    def new(self, category: str) -> int:
        i = self.next
        self.categories[i] = category
        self.next += 1
        return i


def _light(rng: np.random.Generator, elev_deg: tuple[float, float]):
    az = rng.uniform(0, 2 * np.pi)
    el = np.deg2rad(rng.uniform(*elev_deg))
    sun = np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
    sun_rgb = rng.uniform(0.85, 1.15) * np.array([1.0, 0.96, 0.88])
    amb = rng.uniform(0.30, 0.42) * np.array([0.86, 0.93, 1.06])
    return sun, sun_rgb, amb


def _add_tree(prims: Primitives, ids: _Ids, rng: np.random.Generator, x: float, y: float, scale: float = 1.0,
              clear_origin: float | None = None):
    """A trunk and an ellipsoid canopy; with ``clear_origin`` the tree is dropped when its
    canopy would come within that distance of covering the target's centre."""
    r = rng.uniform(2.0, 4.0) * scale
    zc = rng.uniform(4.5, 8.5) * scale
    rz = r * rng.uniform(0.7, 1.0)
    green = np.array([0.20, 0.36, 0.12]) * rng.uniform(0.75, 1.2) + rng.uniform(-0.03, 0.03, 3)
    if clear_origin is not None and np.hypot(x, y) < r + clear_origin:
        return r
    inst = ids.new("tree")
    trunk_top = max(zc - 0.5 * rz, 1.5)
    prims.add_hull(box((x, y), 0.4, 0.4, 0.0, trunk_top), M_BARK, inst, (0.30, 0.22, 0.15))
    prims.add_ellipsoid((x, y, zc), (r, r, rz), M_CANOPY, inst, np.clip(green, 0, 1))
    return r


def _add_building(prims: Primitives, ids: _Ids, rng, cx, cy, size_x, size_y, height) -> None:
    inst = ids.new("building")
    wall = np.array(
        [(0.62, 0.58, 0.52), (0.70, 0.66, 0.60), (0.55, 0.45, 0.38), (0.50, 0.52, 0.55), (0.75, 0.72, 0.66)][
            rng.integers(5)
        ]
    ) * rng.uniform(0.85, 1.1)
    floor_h = rng.uniform(2.9, 3.6)
    spacing = rng.uniform(2.2, 3.4)
    prims.add_hull(box((cx, cy), size_x, size_y, 0.0, height), M_FACADE, inst, np.clip(wall, 0, 1),
                   params=(floor_h, spacing, height, rng.uniform(0.0, 1.0)))
    for _ in range(rng.integers(0, 4)):
        ux, uy = rng.uniform(1.0, min(4.0, size_x / 2)), rng.uniform(1.0, min(4.0, size_y / 2))
        px = cx + rng.uniform(-1, 1) * max(size_x / 2 - ux / 2 - 0.5, 0)
        py = cy + rng.uniform(-1, 1) * max(size_y / 2 - uy / 2 - 0.5, 0)
        prims.add_hull(box((px, py), ux, uy, height, height + rng.uniform(0.8, 2.5)), M_FLAT, inst,
                       (0.55, 0.56, 0.57))


#: Ranges of the urban generator, for the training placement and the shifted one of the
#: hard-test urban contexts. Every shifted range lies outside (or at the edge of) the
#: training range: a narrower street, the target parked closer to a taller anchor building,
#: taller and denser surroundings, more street trees (docs/synthetic_world.md says why).
URBAN_RANGES: dict[str, dict[str, tuple[float, float]]] = {
    "training": {"road_w": (7.0, 12.0), "curb": (1.1, 1.6), "pavement": (2.0, 4.0), "anchor_offset": (0.0, 2.0),
                 "anchor_height": (12.0, 30.0), "p_tree": (0.3, 0.9), "height_base": (5.0, 5.0)},
    "shifted": {"road_w": (5.0, 7.0), "curb": (0.8, 1.1), "pavement": (1.2, 2.0), "anchor_offset": (0.0, 0.0),
                "anchor_height": (30.0, 42.0), "p_tree": (0.9, 1.0), "height_base": (12.0, 12.0)},
}


def _urban(prims: Primitives, ids: _Ids, rng, half_t: float, placement: str = "training"):
    """Street scene in a local frame mirrored by (mx, my); the target (``half_t``: half its
    length) is not mirrored. ``placement`` picks the ranges of :data:`URBAN_RANGES`."""
    rg = URBAN_RANGES[placement]
    mx = float(rng.choice([-1.0, 1.0]))
    my = float(rng.choice([-1.0, 1.0]))
    road_w = rng.uniform(*rg["road_w"])
    curb = rng.uniform(*rg["curb"])
    pw_near, pw_far = rng.uniform(*rg["pavement"]), rng.uniform(*rg["pavement"])
    near_edge = -curb - pw_near  # local x where the near lots begin
    far_edge = road_w - curb + pw_far
    yc = my * rng.uniform(14.0, 40.0)
    cross_w = rng.uniform(7.0, 10.0)
    cross_pw = rng.uniform(2.0, 3.0)
    cross_lo, cross_hi = yc - cross_w / 2 - cross_pw, yc + cross_w / 2 + cross_pw

    def xs(a: float, b: float) -> tuple[float, float]:
        return (min(mx * a, mx * b), max(mx * a, mx * b))

    strips = [
        Strip("y", *xs(-curb, road_w - curb), "road"),
        Strip("y", *xs(near_edge, -curb), "pavement"),
        Strip("y", *xs(road_w - curb, far_edge), "pavement"),
        Strip("x", yc - cross_w / 2, yc + cross_w / 2, "road"),
        Strip("x", cross_lo, cross_hi, "pavement"),
    ]
    footprints: list[tuple[float, float, float, float]] = []
    p_tree = rng.uniform(*rg["p_tree"])
    # the target stands next to a building: an anchor on the near side spanning y = 0
    a_front = rng.uniform(10.0, 24.0)
    a_y0 = -rng.uniform(3.0, a_front - 3.0)
    a_lx0 = near_edge - rng.uniform(*rg["anchor_offset"])
    a_depth = rng.uniform(8.0, 20.0)
    _add_building(prims, ids, rng, mx * (a_lx0 - a_depth / 2), a_y0 + a_front / 2, a_depth, a_front,
                  rng.uniform(*rg["anchor_height"]))
    anchor = (a_y0 - 1.0, a_y0 + a_front + 1.0)
    # building rows on both sides of the street, y from -70 to 70
    for side, edge in ((-1.0, near_edge), (1.0, far_edge)):
        y = -70.0 + rng.uniform(0, 10)
        while y < 70.0:
            front = rng.uniform(8.0, 24.0)
            gap = rng.uniform(0.0, 5.0) if rng.random() > 0.2 else rng.uniform(8.0, 16.0)
            y0, y1 = y, y + front
            y = y1 + gap
            if (y1 > cross_lo and y0 < cross_hi) or (side < 0 and y1 > anchor[0] and y0 < anchor[1]):
                continue
            depth = rng.uniform(8.0, 22.0)
            setback = rng.uniform(0.0, 3.0) if rng.random() > 0.25 else rng.uniform(3.0, 8.0)
            height = rg["height_base"][0] + 35.0 * rng.beta(1.6, 2.4)
            if rng.random() < 0.12 and not (y0 < 3.0 and y1 > -3.0):
                # a small park instead of a building
                for _ in range(rng.integers(2, 6)):
                    tx = edge + side * rng.uniform(3.0, depth)
                    _add_tree(prims, ids, rng, mx * tx, rng.uniform(y0, y1))
                continue
            lx0 = edge + side * setback
            lx1 = lx0 + side * depth
            cx = mx * 0.5 * (lx0 + lx1)
            _add_building(prims, ids, rng, cx, 0.5 * (y0 + y1), depth, front, height)
            footprints.append((*xs(lx0, lx1), y0, y1))
    # street trees on both pavements
    for x_local in (-curb - pw_near / 2, road_w - curb + pw_far / 2):
        y = -60.0 + rng.uniform(0, 8)
        while y < 60.0:
            if not (cross_lo - 1 < y < cross_hi + 1) and rng.random() < p_tree:
                # canopies may overhang the target's ends, never its centre
                _add_tree(prims, ids, rng, mx * (x_local + rng.uniform(-0.3, 0.3)), y, clear_origin=0.5)
            y += rng.uniform(6.0, 11.0)
    # parked cars in both parking lanes
    names = sorted(MODELS)
    for lane_x, yaw in ((0.0, np.pi / 2), (road_w - 2 * curb, -np.pi / 2)):
        for direction in (1.0, -1.0):
            y = direction * half_t if lane_x == 0.0 else -44.0 + rng.uniform(0, 4)
            while abs(y) < 45.0:
                name = names[rng.integers(len(names))]
                length = vehicle_length(name)
                y += direction * (rng.uniform(0.8, 5.0) + length / 2)
                cy = y
                y += direction * length / 2
                if rng.random() < 0.35 or (cross_lo - 3 < cy < cross_hi + 3):
                    continue
                paint = _CAR_PAINTS[rng.integers(len(_CAR_PAINTS))]
                add_vehicle(prims, name, centre=(mx * lane_x, cy), yaw=yaw,
                            instance=ids.new("vehicle"), paint=paint)
            if lane_x != 0.0:
                break
    return strips


def _woodland(prims: Primitives, ids: _Ids, rng, target: str):
    """A wood with a dirt track along x; the target stands in a clearing beside it."""
    my = float(rng.choice([-1.0, 1.0]))
    track_w = rng.uniform(3.0, 4.5)
    t_lo = my * rng.uniform(1.8, 3.5)
    track = (min(t_lo, t_lo + my * track_w), max(t_lo, t_lo + my * track_w))
    strips = [Strip("x", track[0], track[1], "track")]
    clearing = rng.uniform(1.5, 3.5)
    spacing = rng.uniform(4.5, 6.0)
    density = rng.uniform(0.75, 0.95)
    n = int(110 / spacing)
    houses = []
    for _ in range(rng.integers(1, 4)):
        hx = rng.uniform(-45, 45)
        hy = track[1] + rng.uniform(4, 10) if rng.random() < 0.5 else track[0] - rng.uniform(14, 20)
        if abs(hx) < 12:
            continue
        sx, sy = rng.uniform(8, 14), rng.uniform(8, 12)
        _add_building(prims, ids, rng, hx, hy + np.sign(hy) * sy / 2, sx, sy, rng.uniform(5, 12))
        houses.append((hx - sx / 2 - 1, hx + sx / 2 + 1, min(hy, hy + np.sign(hy) * sy) - 1,
                       max(hy, hy + np.sign(hy) * sy) + 1))
    for i in range(n):
        for j in range(n):
            x = -55 + (i + rng.uniform(0.1, 0.9)) * spacing
            y = -55 + (j + rng.uniform(0.1, 0.9)) * spacing
            keep = rng.random() < density
            if not keep or np.hypot(x, y) < clearing or track[0] - 1.0 < y < track[1] + 1.0:
                continue
            if any(a < x < b and c < y < d for a, b, c, d in houses):
                continue
            _add_tree(prims, ids, rng, x, y, scale=rng.uniform(1.1, 1.5))
    names = sorted(MODELS)
    for _ in range(rng.integers(0, 3)):
        cx = rng.choice([-1, 1]) * rng.uniform(7, 30)
        name = names[rng.integers(len(names))]
        add_vehicle(prims, name, centre=(cx, 0.5 * (track[0] + track[1])), yaw=0.0,
                    instance=ids.new("vehicle"), paint=_CAR_PAINTS[rng.integers(len(_CAR_PAINTS))])
    return strips


def _finish(name, context, split, terrain, target, prims, ids, strips, rng, ground_first, elev,
            placement: str = "training") -> Scene:
    sun, sun_rgb, amb = _light(rng, elev)
    grgb, gids, gcats = build_ground(rng, strips, terrain, ground_first)
    cats = {0: "none", **ids.categories, **gcats}
    return Scene(
        name=name, context=context, split=split, terrain=terrain, target=target,
        prims=prims.arrays(), ground_rgb=grgb, ground_ids=gids,
        categories=dict(sorted(cats.items())), sun_dir=sun, sun_rgb=sun_rgb, ambient_rgb=amb,
        look_at=np.array([0.0, 0.0, vehicle_height(target) / 2]), placement=placement,
    )


def _build(name: str, context: int | None, split: str, terrain: str, target: str, rng,
           half_length: float | None = None, placement: str = "training") -> Scene:
    """A context-like scene around ``target`` (urban street or woodland clearing); parked cars
    keep clear of a target ``half_length`` long (default: the target's own half length)."""
    prims = Primitives()
    # ids: 1 target, 2..5 ground regions + strips (built last, ids reserved here), objects after
    n_ground = 4 + 8
    ids = _Ids({TARGET_ID: "target", **{TARGET_ID + 1 + k: "ground" for k in range(n_ground)}})
    add_vehicle(prims, target, centre=(0.0, 0.0), yaw=TARGET_YAW, instance=TARGET_ID)
    if terrain == "urban":
        strips = _urban(prims, ids, rng, vehicle_length(target) / 2 if half_length is None else half_length,
                        placement)
    else:
        strips = _woodland(prims, ids, rng, target)
    for k in range(n_ground):  # drop the reserved ids; build_ground names the ones it uses
        ids.categories.pop(TARGET_ID + 1 + k)
    return _finish(name, context, split, terrain, target, prims, ids, strips, rng, TARGET_ID + 1,
                   SUN_ELEVATION[terrain], placement)


def draw_context(context_id: int, *, seed: int, draw: int, target: str | None = None) -> Scene:
    """Draw number ``draw`` of a context's scene, valid or not (:func:`build_context` gives
    the first valid one)."""
    cid = check_context(context_id)
    terrain, placement = terrain_of(cid)
    rng = np.random.default_rng([int(seed), cid] if draw == 0 else [int(seed), cid, int(draw)])
    scene = _build(scene_name(cid), cid, split_of(cid), terrain, target or target_of(cid), rng,
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


def search_draw(context_id: int, *, seed: int) -> int:
    """The validity search: draws 0, 1, ... of the context until one passes, rendering its
    605 views at the check size (visible fractions only) per draw tried."""
    from .render import render_views

    for draw in range(VALIDITY.max_draws):
        scene = draw_context(context_id, seed=seed, draw=draw)
        if VALIDITY.passes(render_views(scene, VALIDITY.check_size, shade=False).visible, margin=VALIDITY.margin):
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
    from ..grid import N_VIEWS

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
    scene = _build("train_605", None, "train_605", training_stage_terrain(stage), BLOCK_TARGETS[0], rng, longest)
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
    ids = _Ids({TARGET_ID: "target"})
    add_vehicle(prims, target, centre=(0.0, 0.0), yaw=TARGET_YAW, instance=TARGET_ID)
    road_w = rng.uniform(7.0, 11.0)
    curb = rng.uniform(1.1, 1.6)
    strips = [
        Strip("y", -curb, road_w - curb, "road"),
        Strip("y", -curb - 3.0, -curb, "pavement"),
        Strip("y", road_w - curb, road_w - curb + 3.0, "pavement"),
    ]
    return _finish(scene, None, scene, "urban", target, prims, ids, strips, rng, TARGET_ID + 1, (40.0, 70.0))
