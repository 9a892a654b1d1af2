"""Ray casting for the synthetic world's renderer: hulls (convex polyhedra given by their
planes) and ellipsoids against a bundle of rays, and the row gathers and scatters the
renderer and the shading share."""

from __future__ import annotations

import numpy as np

INF = np.inf


def take_rows(a: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """``a[idx]`` for index arrays: ``take`` is several times faster than fancy indexing."""
    return a.take(idx, axis=0)


def put_rows(a: np.ndarray, idx: np.ndarray, v: np.ndarray) -> None:
    """``a[idx] = v`` for (N, C) C-contiguous ``a``: rows moved as single opaque items."""
    row = np.dtype((np.void, a.dtype.itemsize * a.shape[1]))
    np.put(a.view(row).ravel(), idx, np.ascontiguousarray(v, a.dtype).view(row).ravel())


def hull_t(origin_term: np.ndarray, den: np.ndarray, axis: int) -> np.ndarray:
    """Entry distance of rays into a convex hull, ``inf`` on a miss.

    ``origin_term`` (d - n . o) and ``den`` (n . dir) broadcast together with the hull's
    planes along ``axis`` (kept leading so the reduction runs over contiguous slabs). A plane
    parallel to a ray gives t = +-inf (inside / outside its half-space)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        t = origin_term / den
    enter = den < 0
    tn = np.where(enter, t, -INF).max(axis)
    tf = np.where(enter, INF, t).min(axis)
    return np.where((tn <= tf) & (tn > 1e-6), tn, INF)


def hull_cast(origin_term: np.ndarray, den: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`hull_t` for the camera's rays, keeping what finds the entry face: ``origin_term``
    (K, 1) and ``den`` (K, M) for a hull of K planes and M rays give the entry distance (M,)
    (``inf`` on a miss) and the per-plane entry candidates (K, M) (``-inf`` for planes the ray
    leaves through): the face a ray enters through is the plane whose candidate equals the
    entry distance."""
    with np.errstate(divide="ignore", invalid="ignore"):
        t = origin_term / den
    enter = den < 0
    cand = np.where(enter, t, -INF)
    tn = cand.max(0)
    np.copyto(t, INF, where=enter)
    tf = t.min(0)
    return np.where((tn <= tf) & (tn > 1e-6), tn, INF), cand


def ellipsoid_t(o: np.ndarray, d: np.ndarray, centre: np.ndarray, radii: np.ndarray) -> np.ndarray:
    """Nearest positive distance along rays o + t d (o (...,3) or (3,), d (...,3) or (3,))."""
    oo = (o - centre) / radii
    dd = d / radii
    a = np.sum(dd * dd, -1)
    b = 2.0 * np.sum(oo * dd, -1)
    c = np.sum(oo * oo, -1) - 1.0
    disc = b * b - 4 * a * c
    sq = np.sqrt(np.maximum(disc, 0.0))
    t = (-b - sq) / (2 * a)
    return np.where((disc > 0) & (t > 1e-6), t, INF)


def ellipsoid_cast(o: np.ndarray, d: np.ndarray, centre: np.ndarray, radii: np.ndarray) -> np.ndarray:
    """:func:`ellipsoid_t` for rays from one origin ``o`` (3,) along ``d`` (..., 3): the
    quadratic's coefficients as dot products (float64, as there)."""
    inv = 1.0 / (radii * radii)
    oc = o - centre
    a = np.square(d, dtype=np.float64) @ inv
    b = d.astype(np.float64) @ (2.0 * oc * inv)
    c = float(oc * oc @ inv) - 1.0
    disc = b * b - 4 * a * c
    sq = np.sqrt(np.maximum(disc, 0.0))
    t = (-b - sq) / (2 * a)
    return np.where((disc > 0) & (t > 1e-6), t, INF)
