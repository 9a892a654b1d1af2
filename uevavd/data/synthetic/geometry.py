"""Primitives of the synthetic world: convex prisms ("hulls") and ellipsoids.

World frame: metres, x east, y north, z up; the ground is the plane z = 0.

A *hull* is a convex polyhedron stored as ``K`` half-spaces ``n . p <= d`` (padded to
``MAX_PLANES`` with the always-true plane ``0 . p <= 1``) plus its vertices (padded to
``MAX_VERTS`` by repeating the last one) for screen-space culling. Every hull we build is a
convex polygon profile in a vertical (length, height) plane, extruded over a width and
turned by a yaw angle: boxes, car bodies with sloped hoods and windscreens, trunks.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

MAX_PLANES = 8
MAX_VERTS = 12

# Materials: how the renderer textures a surface (see shading._shade).
M_FLAT = 0  # the primitive's colour, no pattern
M_PAINT = 1  # car paint
M_CABIN = 2  # car cabin: painted roof, glass sides
M_TYRE = 3
M_FACADE = 4  # building: windows on walls, gravel roof
M_CANOPY = 5
M_BARK = 6


def prism(
    profile: list[tuple[float, float]],
    half_width: float,
    centre: tuple[float, float],
    yaw: float,
    lateral: float = 0.0,
) -> tuple[np.ndarray, np.ndarray]:
    """Planes (MAX_PLANES, 4) float64 ``[nx, ny, nz, d]`` and vertices (MAX_VERTS, 3) float64
    of a convex profile extruded over ``lateral +- half_width``.

    ``profile``: counter-clockwise polygon in the local (length l, height z) plane, at most
    6 vertices. ``centre`` (x, y) and ``yaw`` (radians, direction of +l from the x axis)
    place the local frame in the world.
    """
    poly = np.asarray(profile, dtype=np.float64)
    if poly.ndim != 2 or poly.shape[1] != 2 or not 3 <= len(poly) <= MAX_PLANES - 2:
        raise ValueError(f"profile must be 3..{MAX_PLANES - 2} (l, z) vertices, got {poly.shape}")
    area = 0.5 * np.sum(poly[:, 0] * np.roll(poly[:, 1], -1) - np.roll(poly[:, 0], -1) * poly[:, 1])
    if area <= 0:
        raise ValueError("profile must be counter-clockwise in the (l, z) plane")
    c, s = np.cos(yaw), np.sin(yaw)
    ax_l = np.array([c, s, 0.0])
    ax_w = np.array([-s, c, 0.0])
    ax_z = np.array([0.0, 0.0, 1.0])
    origin = np.array([centre[0], centre[1], 0.0]) + lateral * ax_w
    planes = np.zeros((MAX_PLANES, 4))
    planes[:, 3] = 1.0
    k = 0
    for i in range(len(poly)):
        p0, p1 = poly[i], poly[(i + 1) % len(poly)]
        e = p1 - p0
        nl, nz = e[1], -e[0]
        norm = np.hypot(nl, nz)
        n = (nl * ax_l + nz * ax_z) / norm
        point = origin + p0[0] * ax_l + p0[1] * ax_z
        planes[k, :3] = n
        planes[k, 3] = n @ point
        k += 1
    for sign in (1.0, -1.0):
        n = sign * ax_w
        planes[k, :3] = n
        planes[k, 3] = n @ (origin + sign * half_width * ax_w)
        k += 1
    verts = [origin + pl * ax_l + pz * ax_z + sw * half_width * ax_w for sw in (1.0, -1.0) for pl, pz in poly]
    while len(verts) < MAX_VERTS:
        verts.append(verts[-1])
    return planes, np.asarray(verts[:MAX_VERTS])


def box(centre: tuple[float, float], length: float, width: float, z0: float, z1: float, yaw: float = 0.0):
    """A box ``length`` along ``yaw``, ``width`` across, from height z0 to z1 (see :func:`prism`)."""
    h = length / 2
    return prism([(-h, z0), (h, z0), (h, z1), (-h, z1)], width / 2, centre, yaw)


@dataclass
class Primitives:
    """Growing lists of primitives, frozen into arrays by :meth:`arrays`.

    Per hull: planes, vertices, material, instance id, RGB colour (0..1), and four
    material parameters (facade: floor height, window spacing, building height, window tint).
    Per ellipsoid: centre, radii, material, instance, colour, parameters.
    """

    h_planes: list = field(default_factory=list)
    h_verts: list = field(default_factory=list)
    h_mat: list = field(default_factory=list)
    h_inst: list = field(default_factory=list)
    h_rgb: list = field(default_factory=list)
    h_par: list = field(default_factory=list)
    e_centre: list = field(default_factory=list)
    e_radii: list = field(default_factory=list)
    e_mat: list = field(default_factory=list)
    e_inst: list = field(default_factory=list)
    e_rgb: list = field(default_factory=list)

    def add_hull(self, hull, material: int, instance: int, rgb, params=(0.0, 0.0, 0.0, 0.0)) -> None:
        planes, verts = hull
        self.h_planes.append(planes)
        self.h_verts.append(verts)
        self.h_mat.append(material)
        self.h_inst.append(instance)
        self.h_rgb.append(tuple(rgb))
        self.h_par.append(tuple(params))

    def add_ellipsoid(self, centre, radii, material: int, instance: int, rgb) -> None:
        self.e_centre.append(tuple(centre))
        self.e_radii.append(tuple(radii))
        self.e_mat.append(material)
        self.e_inst.append(instance)
        self.e_rgb.append(tuple(rgb))

    def arrays(self) -> dict[str, np.ndarray]:
        n_h, n_e = len(self.h_planes), len(self.e_centre)
        return {
            "h_planes": np.asarray(self.h_planes, np.float64).reshape(n_h, MAX_PLANES, 4),
            "h_verts": np.asarray(self.h_verts, np.float64).reshape(n_h, MAX_VERTS, 3),
            "h_mat": np.asarray(self.h_mat, np.int64),
            "h_inst": np.asarray(self.h_inst, np.int64),
            "h_rgb": np.asarray(self.h_rgb, np.float64).reshape(n_h, 3),
            "h_par": np.asarray(self.h_par, np.float64).reshape(n_h, 4),
            "e_centre": np.asarray(self.e_centre, np.float64).reshape(n_e, 3),
            "e_radii": np.asarray(self.e_radii, np.float64).reshape(n_e, 3),
            "e_mat": np.asarray(self.e_mat, np.int64),
            "e_inst": np.asarray(self.e_inst, np.int64),
            "e_rgb": np.asarray(self.e_rgb, np.float64).reshape(n_e, 3),
        }
