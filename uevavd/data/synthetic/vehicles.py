"""The five vehicle models: convex parts with the proportions of the real classes.

Each model is a list of parts ``(profile, half_width, lateral, material)``; a profile is
a counter-clockwise polygon in the car's (length l, height z) plane, l > 0 towards the
front. All five share one paint and one glass colour, so that shape is the only cue:

* hatchback: 3.95 m, short body, cabin reaching the steep rear hatch (short tail);
* pickup: 5.3 m, tall cab and an open bed (low floor inside thin side walls);
* sedan: 4.85 m, cabin in the middle, a long hood and a separate trunk deck;
* sportscar: 4.35 m, low (1.15 m) and wide (2.0 m), cabin set far back;
* suv: 4.75 m, tall (1.8 m) and boxy, the cabin running to a vertical rear.
"""

from __future__ import annotations

from .geometry import M_CABIN, M_PAINT, M_TYRE, Primitives, prism

#: The shared target paint (RGB 0..1): a neutral silver blue.
TARGET_PAINT = (0.62, 0.64, 0.70)

Part = tuple[list[tuple[float, float]], float, float, int]


def _wheels(length_axle: float, half_track: float, radius: float) -> list[Part]:
    parts = []
    for la in (-length_axle / 2, length_axle / 2):
        prof = [(la - radius, 0.0), (la + radius, 0.0), (la + radius, 2 * radius), (la - radius, 2 * radius)]
        for side in (-1, 1):
            parts.append((prof, 0.13, side * half_track, M_TYRE))
    return parts


def _hatchback() -> list[Part]:
    half = 1.75 / 2
    body = [(-1.98, 0.28), (1.98, 0.28), (1.98, 0.68), (1.62, 0.86), (-1.98, 0.92)]
    cabin = [(-1.93, 0.88), (0.70, 0.88), (-0.08, 1.48), (-1.78, 1.48)]
    return [(body, half, 0.0, M_PAINT), (cabin, half * 0.86, 0.0, M_CABIN)] + _wheels(2.45, half - 0.12, 0.31)


def _pickup() -> list[Part]:
    half = 2.0 / 2
    front = [(-0.45, 0.45), (2.65, 0.45), (2.65, 1.00), (2.30, 1.12), (-0.45, 1.12)]
    cab = [(-0.45, 1.08), (1.05, 1.08), (0.55, 1.85), (-0.40, 1.85)]
    floor = [(-2.65, 0.45), (-0.45, 0.45), (-0.45, 0.70), (-2.65, 0.70)]
    side_wall = [(-2.65, 0.45), (-0.45, 0.45), (-0.45, 1.15), (-2.65, 1.15)]
    tail = [(-2.65, 0.45), (-2.53, 0.45), (-2.53, 1.12), (-2.65, 1.12)]
    head = [(-0.62, 0.45), (-0.45, 0.45), (-0.45, 1.15), (-0.62, 1.15)]
    return [
        (front, half, 0.0, M_PAINT),
        (cab, half * 0.9, 0.0, M_CABIN),
        (floor, half, 0.0, M_PAINT),
        (side_wall, 0.06, half - 0.06, M_PAINT),
        (side_wall, 0.06, -(half - 0.06), M_PAINT),
        (tail, half, 0.0, M_PAINT),
        (head, half, 0.0, M_PAINT),
    ] + _wheels(3.3, half - 0.13, 0.40)


def _sedan() -> list[Part]:
    half = 1.80 / 2
    body = [(-2.43, 0.28), (2.43, 0.28), (2.43, 0.66), (2.13, 0.82), (-2.43, 0.90)]
    cabin = [(-1.25, 0.86), (1.05, 0.86), (0.25, 1.45), (-0.75, 1.45)]
    return [(body, half, 0.0, M_PAINT), (cabin, half * 0.86, 0.0, M_CABIN)] + _wheels(2.85, half - 0.12, 0.32)


def _sportscar() -> list[Part]:
    half = 2.0 / 2
    body = [(-2.18, 0.16), (2.18, 0.16), (2.18, 0.42), (1.15, 0.70), (-2.18, 0.74)]
    cabin = [(-1.65, 0.70), (0.50, 0.70), (-0.30, 1.15), (-1.20, 1.15)]
    return [(body, half, 0.0, M_PAINT), (cabin, half * 0.78, 0.0, M_CABIN)] + _wheels(2.6, half - 0.14, 0.33)


def _suv() -> list[Part]:
    half = 1.95 / 2
    body = [(-2.38, 0.42), (2.38, 0.42), (2.38, 0.95), (2.05, 1.08), (-2.38, 1.10)]
    cabin = [(-2.32, 1.06), (1.25, 1.06), (0.65, 1.80), (-2.28, 1.80)]
    return [(body, half, 0.0, M_PAINT), (cabin, half * 0.93, 0.0, M_CABIN)] + _wheels(2.9, half - 0.13, 0.40)


MODELS = {
    "hatchback": _hatchback,
    "pickup": _pickup,
    "sedan": _sedan,
    "sportscar": _sportscar,
    "suv": _suv,
}


def vehicle_height(name: str) -> float:
    """Roof height of a model in metres (the camera looks at half of it)."""
    return max(z for prof, *_ in model_parts(name) for _, z in prof)


def vehicle_length(name: str) -> float:
    parts = model_parts(name)
    return max(lv for prof, *_ in parts for lv, _ in prof) - min(lv for prof, *_ in parts for lv, _ in prof)


def model_parts(name: str) -> list[Part]:
    """The parts of a model; an unknown name lists the five."""
    if name not in MODELS:
        raise ValueError(f"unknown vehicle model {name!r}: expected one of {sorted(MODELS)}")
    return MODELS[name]()


def add_vehicle(
    prims: Primitives,
    name: str,
    *,
    centre: tuple[float, float],
    yaw: float,
    instance: int,
    paint: tuple[float, float, float] = TARGET_PAINT,
) -> None:
    """Append the parts of model ``name`` at ``centre`` (x, y metres) heading ``yaw`` (radians)."""
    glass = (0.10, 0.12, 0.15)
    tyre = (0.05, 0.05, 0.05)
    for profile, half_width, lateral, material in model_parts(name):
        hull = prism(profile, half_width, centre, yaw, lateral)
        rgb = tyre if material == M_TYRE else paint
        prims.add_hull(hull, material, instance, rgb, params=(*glass, 0.0))
