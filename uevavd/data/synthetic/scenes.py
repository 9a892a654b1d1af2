"""The procedural scenes of the synthetic world: what stands around the target in an urban
street or a woodland clearing, the ground and the light (:func:`build_scene`). Which draw a
context uses, and the validity rule, are :mod:`uevavd.data.synthetic.world`'s."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .geometry import M_BARK, M_CANOPY, M_FACADE, M_FLAT, Primitives, box
from .ground import Strip, build_ground
from .vehicles import MODELS, add_vehicle, vehicle_height, vehicle_length

TARGET_ID = 1
TARGET_YAW = np.pi / 2  # heading +y (north)
#: Sun elevation range (degrees) per terrain.
SUN_ELEVATION = {"urban": (35.0, 72.0), "woodland": (28.0, 65.0)}
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


class InstanceIds:
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


def _add_tree(prims: Primitives, ids: InstanceIds, rng: np.random.Generator, x: float, y: float, scale: float = 1.0,
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


def _add_building(prims: Primitives, ids: InstanceIds, rng, cx, cy, size_x, size_y, height) -> None:
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


def _urban(prims: Primitives, ids: InstanceIds, rng, half_t: float, placement: str = "training"):
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


def _woodland(prims: Primitives, ids: InstanceIds, rng, target: str):
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


def finish_scene(name, context, split, terrain, target, prims, ids, strips, rng, ground_first, elev,
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


def build_scene(name: str, context: int | None, split: str, terrain: str, target: str, rng,
           half_length: float | None = None, placement: str = "training") -> Scene:
    """A context-like scene around ``target`` (urban street or woodland clearing); parked cars
    keep clear of a target ``half_length`` long (default: the target's own half length)."""
    prims = Primitives()
    # ids: 1 target, 2..5 ground regions + strips (built last, ids reserved here), objects after
    n_ground = 4 + 8
    ids = InstanceIds({TARGET_ID: "target", **{TARGET_ID + 1 + k: "ground" for k in range(n_ground)}})
    add_vehicle(prims, target, centre=(0.0, 0.0), yaw=TARGET_YAW, instance=TARGET_ID)
    if terrain == "urban":
        strips = _urban(prims, ids, rng, vehicle_length(target) / 2 if half_length is None else half_length,
                        placement)
    else:
        strips = _woodland(prims, ids, rng, target)
    for k in range(n_ground):  # drop the reserved ids; build_ground names the ones it uses
        ids.categories.pop(TARGET_ID + 1 + k)
    return finish_scene(name, context, split, terrain, target, prims, ids, strips, rng, TARGET_ID + 1,
                   SUN_ELEVATION[terrain], placement)

