"""Pinhole camera and analytic ray caster for the synthetic world (numpy, one process).

Camera: at a grid viewpoint, looking at the target's centre; image "up" is world +y
projected onto the image plane; focal length ``f = 8 * size`` px (a 256 px crop out of a
4096 px wide, 90 degree frame is f = 2048 px at 256 px). Pixel (u, v) has its centre at
(u + 0.5, v + 0.5); u grows to the right, v downwards.

Method (measured in ``benchmarks/bench_render.py``): per view, primitives whose bounding
sphere lies outside the view frustum are dropped; the others are projected to the screen
(their vertices, or the corners of their boxes for ellipsoids) and each is ray-cast only over
the pixel rectangle it covers, so the narrow frustum culls almost the whole world. The
ground plane is intersected analytically for every pixel. Shadows: one lookup per pixel in
a shadow map cast from the sun, built tile by tile the first time a view needs a tile and
kept for the scene (see :class:`_ShadowMap`). Per-pixel shading works on index arrays
(``take`` / ``put``), and each texture only on the pixels it applies to.
Shading: Lambert with the sun (coloured) and a sky-weighted ambient term, procedural
textures for facades (windows), canopies (leaf clumps), glass and the ground map.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..grid import N_VIEWS, view_coords
from .geometry import M_CABIN, M_CANOPY, M_FACADE
from .ground import lookup
from .scenes import TARGET_ID, Scene

_INF = np.inf


def _rows(a: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """``a[idx]`` for index arrays: ``take`` is several times faster than fancy indexing."""
    return a.take(idx, axis=0)


def _put_rows(a: np.ndarray, idx: np.ndarray, v: np.ndarray) -> None:
    """``a[idx] = v`` for (N, C) C-contiguous ``a``: rows moved as single opaque items."""
    row = np.dtype((np.void, a.dtype.itemsize * a.shape[1]))
    np.put(a.view(row).ravel(), idx, np.ascontiguousarray(v, a.dtype).view(row).ravel())


@dataclass
class View:
    """One rendered view: ``rgb`` (H, W, 3) uint8; ``seg`` (H, W) uint16 instance ids;
    ``box`` (4,) int32 XYXY pixels over visible target pixels, x2/y2 exclusive,
    [0, 0, 0, 0] when none is visible; ``visible`` float: visible target pixels / target
    pixels with occluders removed; ``occluders``: sorted instance ids drawn over the
    target's pixels (empty when it is fully visible)."""

    rgb: np.ndarray
    seg: np.ndarray
    box: np.ndarray
    visible: float
    occluders: tuple[int, ...] = ()


@dataclass
class ContextViews:
    """All 605 views of one scene, in grid view order: ``rgb`` (605, H, W, 3) uint8,
    ``seg`` (605, H, W) uint16, ``boxes`` (605, 4) int32 XYXY (x2, y2 exclusive),
    ``visible`` (605,) float32, ``categories`` {instance id: category}, ``target`` name."""

    rgb: np.ndarray
    seg: np.ndarray
    boxes: np.ndarray
    visible: np.ndarray
    categories: dict[int, str]
    target: str


def focal_px(size: int) -> float:
    """Focal length in pixels for a ``size`` px crop (8 * size)."""
    return 8.0 * size


def camera_basis(position: np.ndarray, look_at: np.ndarray) -> np.ndarray:
    """(3, 3) rows: forward, right, up (unit vectors, world frame)."""
    f = np.asarray(look_at, np.float64) - np.asarray(position, np.float64)
    f /= np.linalg.norm(f)
    up = np.array([0.0, 1.0, 0.0]) - f[1] * f
    n = np.linalg.norm(up)
    if n < 1e-9:
        raise ValueError(f"camera at {position} looks along the y axis: image up is undefined")
    up /= n
    right = np.cross(f, up)
    return np.stack([f, right, up])


class _Prep:
    """Per-scene precomputation: float32 copies of the primitives, bounding spheres (frustum
    culling), real plane counts, lookup tables for shading, ellipsoid corner boxes."""

    def __init__(self, scene: Scene):
        p = scene.prims
        self.p = dict(p)
        for key in ("h_planes", "h_rgb", "h_par", "e_rgb"):
            self.p[key] = p[key].astype(np.float32)
        p = self.p
        inst = p["h_inst"]
        self.h_target = inst == TARGET_ID
        # real planes come first in every hull; padding planes (0 . p <= 1) are skipped
        n_real = (np.abs(p["h_planes"][..., :3]).sum(-1) > 0).sum(-1) if len(inst) else np.zeros(0, np.int64)
        self.h_nk = n_real.tolist()
        hv = p["h_verts"]
        self.h_c = hv.mean(1) if len(inst) else np.zeros((0, 3))  # bounding spheres
        self.h_r = np.linalg.norm(hv - self.h_c[:, None], axis=2).max(1) if len(inst) else np.zeros(0)
        # per (hull, plane) unit normals, row hull * MAX_PLANES + plane; glass colours
        self.h_normals = np.ascontiguousarray(p["h_planes"][..., :3].reshape(-1, 3))
        self.h_k = p["h_planes"].shape[1] if len(inst) else 1
        self.h_glass = np.ascontiguousarray(p["h_par"][:, :3])
        self.e_c = p["e_centre"]
        self.e_c32 = self.e_c.astype(np.float32)
        self.e_inv_r2 = (1.0 / p["e_radii"] ** 2).astype(np.float32)
        self.e_r = p["e_radii"].max(1) if len(self.e_c) else np.zeros(0)
        signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], np.float64)
        self.e_corners = self.e_c[:, None, :] + signs[None] * p["e_radii"][:, None, :]
        self._shadow: dict = {}

    def shadow_map(self, sun: np.ndarray, size: int) -> _ShadowMap:
        """The scene's cached shadow map for crops of ``size`` px (cells ~0.8 of the pixel
        footprint at the nearest viewpoint, 60 m)."""
        key = (size, *np.round(sun, 9))
        if key not in self._shadow:
            self._shadow[key] = _ShadowMap(self, sun, 0.8 * 60.0 / focal_px(size))
        return self._shadow[key]

    def rects(self, origin, basis, size: int, fpx: float, cull: bool = True) -> tuple[np.ndarray, np.ndarray]:
        """(H, 4) and (E, 4) pixel rectangles [y0, y1, x0, x1] of the hulls and ellipsoids.
        With ``cull``, primitives whose bounding sphere lies outside the view frustum get an
        empty rectangle without projecting their vertices (no ray of the crop can hit them);
        without it every rectangle is the whole frame."""
        out = []
        for centre, radius, points in ((self.h_c, self.h_r, self.p["h_verts"]), (self.e_c, self.e_r, self.e_corners)):
            r = np.zeros((len(centre), 4), np.int64)
            if cull:
                keep = np.flatnonzero(_in_frustum(centre, radius, origin, basis, size, fpx))
                r[keep] = _rects(points[keep], origin, basis, size, fpx)
            else:
                r[:] = (0, size, 0, size)
            out.append(r)
        return out[0], out[1]


def _in_frustum(centre: np.ndarray, radius: np.ndarray, origin, basis, size: int, fpx: float) -> np.ndarray:
    """(P,) bool: spheres (centres (P, 3), radii (P,)) that may reach into the view frustum of a
    ``size`` px crop (conservative: a sphere outside one of its four side planes, or wholly
    behind the camera, is out)."""
    q = (centre - origin) @ basis.T  # depth, x, y
    tan = 0.5 * size / fpx
    k = 1.0 / np.sqrt(1.0 + tan * tan)  # side planes' distances: (|x| - depth tan) k
    r = radius * 1.001 + 1e-3
    side = (np.maximum(np.abs(q[:, 1]), np.abs(q[:, 2])) - q[:, 0] * tan) * k
    return (side < r) & (q[:, 0] > -r)


def _rects(points: np.ndarray, origin, basis, size: int, fpx: float) -> np.ndarray:
    """(P, 4) int64 pixel rectangles [y0, y1, x0, x1] covering projected point sets (P, M, 3)."""
    if len(points) == 0:
        return np.zeros((0, 4), np.int64)
    q = (points - origin) @ basis.T  # (P, M, 3): depth, x, y
    depth = q[..., 0]
    behind = (depth < 0.1).any(1)
    depth = np.maximum(depth, 0.1)
    px = fpx * q[..., 1] / depth + size / 2
    py = size / 2 - fpx * q[..., 2] / depth
    x0 = np.floor(px.min(1)).astype(np.int64)
    x1 = np.ceil(px.max(1)).astype(np.int64) + 1
    y0 = np.floor(py.min(1)).astype(np.int64)
    y1 = np.ceil(py.max(1)).astype(np.int64) + 1
    r = np.stack([np.clip(y0, 0, size), np.clip(y1, 0, size), np.clip(x0, 0, size), np.clip(x1, 0, size)], 1)
    r[behind] = (0, size, 0, size)
    return r


def _hull_t(origin_term: np.ndarray, den: np.ndarray, axis: int) -> np.ndarray:
    """Entry distance of rays into a convex hull, ``inf`` on a miss.

    ``origin_term`` (d - n . o) and ``den`` (n . dir) broadcast together with the hull's
    planes along ``axis`` (kept leading so the reduction runs over contiguous slabs). A plane
    parallel to a ray gives t = +-inf (inside / outside its half-space)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        t = origin_term / den
    enter = den < 0
    tn = np.where(enter, t, -_INF).max(axis)
    tf = np.where(enter, _INF, t).min(axis)
    return np.where((tn <= tf) & (tn > 1e-6), tn, _INF)


def _hull_cast(origin_term: np.ndarray, den: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`_hull_t` for the camera's rays, keeping what finds the entry face: ``origin_term``
    (K, 1) and ``den`` (K, M) for a hull of K planes and M rays give the entry distance (M,)
    (``inf`` on a miss) and the per-plane entry candidates (K, M) (``-inf`` for planes the ray
    leaves through): the face a ray enters through is the plane whose candidate equals the
    entry distance."""
    with np.errstate(divide="ignore", invalid="ignore"):
        t = origin_term / den
    enter = den < 0
    cand = np.where(enter, t, -_INF)
    tn = cand.max(0)
    np.copyto(t, _INF, where=enter)
    tf = t.min(0)
    return np.where((tn <= tf) & (tn > 1e-6), tn, _INF), cand


def _ellipsoid_t(o: np.ndarray, d: np.ndarray, centre: np.ndarray, radii: np.ndarray) -> np.ndarray:
    """Nearest positive distance along rays o + t d (o (...,3) or (3,), d (...,3) or (3,))."""
    oo = (o - centre) / radii
    dd = d / radii
    a = np.sum(dd * dd, -1)
    b = 2.0 * np.sum(oo * dd, -1)
    c = np.sum(oo * oo, -1) - 1.0
    disc = b * b - 4 * a * c
    sq = np.sqrt(np.maximum(disc, 0.0))
    t = (-b - sq) / (2 * a)
    return np.where((disc > 0) & (t > 1e-6), t, _INF)


def _ellipsoid_cast(o: np.ndarray, d: np.ndarray, centre: np.ndarray, radii: np.ndarray) -> np.ndarray:
    """:func:`_ellipsoid_t` for rays from one origin ``o`` (3,) along ``d`` (..., 3): the
    quadratic's coefficients as dot products (float64, as there)."""
    inv = 1.0 / (radii * radii)
    oc = o - centre
    a = np.square(d, dtype=np.float64) @ inv
    b = d.astype(np.float64) @ (2.0 * oc * inv)
    c = float(oc * oc @ inv) - 1.0
    disc = b * b - 4 * a * c
    sq = np.sqrt(np.maximum(disc, 0.0))
    t = (-b - sq) / (2 * a)
    return np.where((disc > 0) & (t > 1e-6), t, _INF)


def _pixel_dirs(size: int, basis: np.ndarray) -> np.ndarray:
    """(size, size, 3) float32 ray directions through the pixel centres (not normalised)."""
    c = np.arange(size, dtype=np.float64) + 0.5 - size / 2
    f, right, up = basis
    # the sum of a row term and a column term, in float64, rounded once to float32
    out = np.empty((size, size, 3), np.float32)
    np.add((focal_px(size) * f)[None, None] + c[None, :, None] * right, (-c)[:, None, None] * up, out=out)
    return out


def render_view(scene: Scene, view: int, size: int, prep: _Prep | None = None, *, cull: bool = True,
                exclude: tuple[int, ...] = (), shade: bool = True) -> View:
    """Render one viewpoint (grid index 0..604) of ``scene`` at ``size`` x ``size`` px.

    ``cull=False`` casts every primitive over the whole frame (the slow reference the
    benchmark compares against; the images are identical). ``exclude``: instance ids the
    camera does not see (they still cast their shadows). ``shade=False`` skips the colours
    (``rgb`` is then all zeros; segmentation, box and visible fraction are unchanged): the
    validity rule needs only the visible fractions."""
    prep = prep or _Prep(scene)
    p = prep.p
    origin = view_coords(view)
    basis = camera_basis(origin, scene.look_at)
    fpx = focal_px(size)
    dirs = _pixel_dirs(size, basis)  # (H, W, 3) float32, not normalised
    # ground plane z = 0 (every ray looks down)
    tbest = (-origin[2] / dirs[..., 2]).astype(np.float32)
    kind = np.zeros((size, size), np.int8)  # 0 ground, 1 hull, 2 ellipsoid
    pid = np.zeros((size, size), np.int64)
    face = np.zeros((size, size), np.int8)  # hulls: the plane the ray enters through
    ttar = np.full((size, size), _INF, np.float32)
    h_rects, e_rects = prep.rects(origin, basis, size, fpx, cull)
    if len(exclude):
        h_rects[np.isin(p["h_inst"], exclude)] = 0
        e_rects[np.isin(p["e_inst"], exclude)] = 0
    tbest_f, kind_f, pid_f, face_f = tbest.ravel(), kind.ravel(), pid.ravel(), face.ravel()
    # every hull over its own rectangle, in index order (ties go to the lower index)
    h_ot = (p["h_planes"][..., 3] - p["h_planes"][..., :3] @ origin).astype(np.float32)  # (H, K): d - n . o
    for i in np.flatnonzero((h_rects[:, 0] < h_rects[:, 1]) & (h_rects[:, 2] < h_rects[:, 3])).tolist():
        y0, y1, x0, x1 = h_rects[i].tolist()
        k = prep.h_nk[i]
        d = dirs[y0:y1, x0:x1]
        hh, ww = y1 - y0, x1 - x0
        den = p["h_planes"][i, :k, :3] @ d.reshape(-1, 3).T  # (K, M)
        t, cand = _hull_cast(h_ot[i, :k, None], den)  # (M,), (K, M)
        t2 = t.reshape(hh, ww)
        if prep.h_target[i]:
            np.minimum(ttar[y0:y1, x0:x1], t2, out=ttar[y0:y1, x0:x1])
        better = t2 < tbest[y0:y1, x0:x1]
        m = np.flatnonzero(better)  # the rays this hull now owns
        if not len(m):
            continue
        np.copyto(tbest[y0:y1, x0:x1], t2, where=better)
        np.copyto(kind[y0:y1, x0:x1], 1, where=better)
        np.copyto(pid[y0:y1, x0:x1], i, where=better)
        # entry face: the first plane whose entry candidate is the entry distance
        n_m = hh * ww
        faces = (cand.ravel().take(m[:, None] + np.arange(k) * n_m) == t.take(m)[:, None]).argmax(1)
        face_f.put((m // ww + y0) * size + (m % ww + x0), faces)
    for i in np.flatnonzero((e_rects[:, 0] < e_rects[:, 1]) & (e_rects[:, 2] < e_rects[:, 3])).tolist():
        y0, y1, x0, x1 = e_rects[i].tolist()
        t = _ellipsoid_cast(origin, dirs[y0:y1, x0:x1], p["e_centre"][i], p["e_radii"][i])
        better = t < tbest[y0:y1, x0:x1]
        np.copyto(tbest[y0:y1, x0:x1], t, where=better)
        np.copyto(kind[y0:y1, x0:x1], 2, where=better)
        np.copyto(pid[y0:y1, x0:x1], i, where=better)
    pts = origin.astype(np.float32) + tbest_f[:, None] * dirs.reshape(-1, 3)  # (N, 3) hit points
    ground_rgb, seg = lookup(scene.ground_rgb, scene.ground_ids, pts[:, 0], pts[:, 1])
    h, e = np.flatnonzero(kind_f == 1), np.flatnonzero(kind_f == 2)
    seg.put(h, p["h_inst"].take(pid_f.take(h)))
    seg.put(e, p["e_inst"].take(pid_f.take(e)))
    seg = seg.reshape(size, size)
    rgb = (_shade(scene, prep, pts, ground_rgb, h, e, pid_f, face_f).reshape(size, size, 3) if shade
           else np.zeros((size, size, 3), np.uint8))
    vis = seg == TARGET_ID
    whole = np.isfinite(ttar)
    full = int(whole.sum())
    n_vis = int(vis.sum())
    if n_vis:
        ys, xs = np.nonzero(vis)
        bx = np.array([xs.min(), ys.min(), xs.max() + 1, ys.max() + 1], np.int32)
    else:
        bx = np.zeros(4, np.int32)
    occluders = tuple(int(i) for i in np.unique(seg[whole & ~vis])) if n_vis < full else ()
    return View(rgb=rgb, seg=seg, box=bx, visible=float(n_vis / full) if full else 0.0, occluders=occluders)


def render_unoccluded_view(scene: Scene, view: int, size: int, prep: _Prep | None = None) -> View:
    """Render a view with every object that would hide part of the target left out of it
    (their shadows stay, as those of objects just outside the crop would): the target is
    fully visible, the rest of the scene as it is. One render when nothing hides the
    target; otherwise the objects drawn over it are left out and the view rendered again,
    until none is (an object behind a removed one may show up in its place)."""
    prep = prep or _Prep(scene)
    v = render_view(scene, view, size, prep)
    exclude: tuple[int, ...] = ()
    while v.occluders:
        exclude = tuple(sorted({*exclude, *v.occluders}))
        v = render_view(scene, view, size, prep, exclude=exclude)
    return v


class _ShadowMap:
    """Lazily built, cached shadow map of a scene (the sun and the geometry are static).

    Frame (u, v, a) with a along the sun. The (u, v) plane is cut into tiles of ``TILE`` x
    ``TILE`` cells of ``cell`` metres; a tile holds, per cell, the highest a at which an
    orthographic ray from the sun enters a primitive, cast only against the primitives whose
    projected vertices overlap the tile. Tiles are computed the first time a view needs them
    and reused by every later view."""

    TILE = 128

    def __init__(self, prep: _Prep, sun: np.ndarray, cell: float):
        p = prep.p
        lit_u = np.cross(sun, [0.0, 0.0, 1.0] if abs(sun[2]) < 0.99 else [1.0, 0.0, 0.0])
        lit_u /= np.linalg.norm(lit_u)
        self.frame = np.stack([lit_u, np.cross(sun, lit_u), sun])  # rows u, v, a
        self.frame32 = self.frame.astype(np.float32)
        self.sun = sun
        self.cell = cell
        self.inv_cell = np.float32(1.0 / cell)
        # computed tiles live in one atlas (rows v, columns u) whose tile (0, 0) is tile
        # (tu0, tv0); ``done`` marks the computed ones. Grown on demand, never shrunk.
        self.atlas = np.empty((0, 0), np.float32)
        self.done = np.zeros((0, 0), bool)
        self.tu0 = self.tv0 = 0
        self.prims = []  # (kind, index, ulo, uhi, vlo, vhi)
        for kind, corners in (("h", p["h_verts"]), ("e", prep.e_corners)):
            if len(corners):
                proj = corners @ self.frame.T
                lo, hi = proj.min(1), proj.max(1)
                self.prims.append((kind, lo[:, 0], hi[:, 0], lo[:, 1], hi[:, 1]))
        self.p = p

    def _tile(self, tu: int, tv: int) -> np.ndarray:
        span = self.TILE * self.cell
        u0, v0 = tu * span, tv * span
        cu = u0 + (np.arange(self.TILE) + 0.5) * self.cell
        cv = v0 + (np.arange(self.TILE) + 0.5) * self.cell
        top = 200.0  # sun rays start above everything (a < 200 m for every primitive)
        depth = np.full((self.TILE, self.TILE), -_INF, np.float32)
        fu, fv, sun = self.frame[0], self.frame[1], self.sun
        for kind, ulo, uhi, vlo, vhi in self.prims:
            hit = np.nonzero((ulo < u0 + span) & (uhi > u0) & (vlo < v0 + span) & (vhi > v0))[0]
            for i in hit:
                i0 = max(int((ulo[i] - u0) / self.cell), 0)
                i1 = min(int((uhi[i] - u0) / self.cell) + 2, self.TILE)
                j0 = max(int((vlo[i] - v0) / self.cell), 0)
                j1 = min(int((vhi[i] - v0) / self.cell) + 2, self.TILE)
                o = (cu[None, i0:i1, None] * fu + cv[j0:j1, None, None] * fv + top * sun).reshape(-1, 3)
                if kind == "h":
                    pl = self.p["h_planes"][i].astype(np.float64)
                    t = _hull_t(pl[:, 3, None] - pl[:, :3] @ o.T, -(pl[:, :3] @ sun)[:, None], 0)
                else:
                    t = _ellipsoid_t(o, -sun, self.p["e_centre"][i], self.p["e_radii"][i])
                sub = depth[j0:j1, i0:i1]
                np.maximum(sub, (top - t).reshape(sub.shape), out=sub)
        return depth

    def _cover(self, u_lo: int, u_hi: int, v_lo: int, v_hi: int) -> None:
        """Make sure tiles u_lo..u_hi x v_lo..v_hi are computed and in the atlas."""
        t, (nv, nu) = self.TILE, self.done.shape
        if not (self.tu0 <= u_lo and u_hi < self.tu0 + nu and self.tv0 <= v_lo and v_hi < self.tv0 + nv):
            # grow with a margin of two tiles on each side (views move across the ground)
            if nu:
                u_lo2, u_hi2 = min(u_lo, self.tu0) - 2, max(u_hi, self.tu0 + nu - 1) + 2
                v_lo2, v_hi2 = min(v_lo, self.tv0) - 2, max(v_hi, self.tv0 + nv - 1) + 2
            else:
                u_lo2, u_hi2, v_lo2, v_hi2 = u_lo - 2, u_hi + 2, v_lo - 2, v_hi + 2
            atlas = np.empty(((v_hi2 - v_lo2 + 1) * t, (u_hi2 - u_lo2 + 1) * t), np.float32)
            done = np.zeros((v_hi2 - v_lo2 + 1, u_hi2 - u_lo2 + 1), bool)
            du, dv = self.tu0 - u_lo2, self.tv0 - v_lo2
            atlas[dv * t:(dv + nv) * t, du * t:(du + nu) * t] = self.atlas
            done[dv:dv + nv, du:du + nu] = self.done
            self.atlas, self.done, self.tu0, self.tv0 = atlas, done, u_lo2, v_lo2
        for b, a in zip(*np.nonzero(~self.done[v_lo - self.tv0:v_hi - self.tv0 + 1, u_lo - self.tu0:u_hi - self.tu0 + 1]),
                        strict=True):
            a, b = int(a) + u_lo, int(b) + v_lo
            i, j = (a - self.tu0) * t, (b - self.tv0) * t
            self.atlas[j:j + t, i:i + t] = self._tile(a, b)
            self.done[b - self.tv0, a - self.tu0] = True

    def shadowed(self, pts: np.ndarray, lam: np.ndarray, bias: np.ndarray) -> np.ndarray:
        """(N,) bool: points (N, 3) hidden from the sun; ``lam`` (N,) their Lambert term (the
        depth bias grows with the grazing angle) and ``bias`` (N,) extra metres of bias."""
        q = pts @ self.frame32.T  # float32: a cell is >= 2 cm, the depth bias >= 4 cm
        iu = np.floor(q[:, 0] * self.inv_cell).astype(np.int64)
        iv = np.floor(q[:, 1] * self.inv_cell).astype(np.int64)
        t = self.TILE
        self._cover(int(iu.min()) // t, int(iu.max()) // t, int(iv.min()) // t, int(iv.max()) // t)
        iv -= self.tv0 * t
        iv *= self.atlas.shape[1]
        iv += iu
        iv -= self.tu0 * t
        depth = self.atlas.ravel().take(iv)
        slope = np.sqrt(np.maximum(1.0 - lam * lam, 0.0)) / np.maximum(lam, 0.2)
        return q[:, 2] < depth - (0.04 + bias + 1.5 * self.cell * slope)


def _wave_noise(pts: np.ndarray, freq: float, comps: tuple[int, ...] = (0, 1, 2)) -> np.ndarray:
    """Cheap deterministic 3D pattern in about [-1, 1], (N, 3) -> (N, len(comps)); only the
    components ``comps`` are computed (each costs two sines per point)."""
    x, y, z = pts[:, 0] * freq, pts[:, 1] * freq, pts[:, 2] * freq
    f = (lambda: np.sin(x * 1.7 + np.sin(y * 2.3 + z)), lambda: np.sin(y * 1.9 + np.sin(z * 2.1 + x)),
         lambda: np.sin(z * 2.2 + np.sin(x * 1.3 + y)))
    return np.stack([f[c]() for c in comps], 1)


def _shade(scene: Scene, prep: _Prep, pts, ground_rgb, h, e, pid, face) -> np.ndarray:
    """(N, 3) uint8 colours of hit points ``pts`` (N, 3); ``h`` / ``e``: indices of pixels that
    hit a hull / an ellipsoid (the rest hit the ground, coloured ``ground_rgb``); ``pid`` (N,)
    the primitive hit and ``face`` (N,) the plane of its hull the ray entered through."""
    p = prep.p
    size = int(round(np.sqrt(len(pts))))
    normal = np.zeros(pts.shape, np.float32)
    normal[:, 2] = 1.0
    col = ground_rgb  # a fresh array (gathered from the map)
    bias = np.zeros(len(pts), np.float32)  # canopies: bumpy normals on a smooth ellipsoid
    if len(h):
        hp = pid.take(h)
        nh = _rows(prep.h_normals, hp * prep.h_k + face.take(h))
        _put_rows(normal, h, nh)
        c = _rows(p["h_rgb"], hp)
        mat = p["h_mat"].take(hp)
        cab = np.flatnonzero((mat == M_CABIN) & (nh[:, 2] < 0.9))  # glass
        if len(cab):
            _put_rows(c, cab, _rows(prep.h_glass, hp.take(cab)))
        fac = np.flatnonzero(mat == M_FACADE)
        if len(fac):
            _put_rows(c, fac, _facade(_rows(pts, h.take(fac)), _rows(nh, fac), _rows(c, fac), _rows(p["h_par"], hp.take(fac))))
        _put_rows(col, h, c)
    if len(e):
        ep = pid.take(e)
        pe = _rows(pts, e)
        n = (pe - _rows(prep.e_c32, ep)) * _rows(prep.e_inv_r2, ep)  # gradient of the ellipsoid's equation
        c = _rows(p["e_rgb"], ep)
        can = np.flatnonzero(p["e_mat"].take(ep) == M_CANOPY)
        if len(can) == len(e):  # woodland: every ellipsoid is a canopy
            wn = _wave_noise(pe, 1.6)
            n = _unit(n) + 0.55 * wn
            c *= 1.0 + 0.18 * wn[:, :1]
        elif len(can):
            wn = _wave_noise(_rows(pe, can), 1.6)
            _put_rows(n, can, _unit(_rows(n, can)) + 0.55 * wn)
            _put_rows(c, can, _rows(c, can) * (1.0 + 0.18 * wn[:, :1]))
        _put_rows(normal, e, _unit(n))
        _put_rows(col, e, c)
        bias.put(e, 0.6)
    sun = scene.sun_dir.astype(np.float32)
    lam = normal @ sun
    np.clip(lam, 0.0, 1.0, out=lam)
    lam[prep.shadow_map(scene.sun_dir, size).shadowed(pts, lam, bias)] = 0.0
    # light = ambient * (0.65 + 0.35 n_z) + sun * lambert, as one (N, 3) @ (3, 3) product
    amb, sun_rgb = (scene.ambient_rgb * 255.0).astype(np.float32), (scene.sun_rgb * 255.0).astype(np.float32)
    terms = np.empty((len(pts), 3), np.float32)
    terms[:, 0] = 1.0
    terms[:, 1] = normal[:, 2]
    terms[:, 2] = lam
    out = terms @ np.stack([0.65 * amb, 0.35 * amb, sun_rgb])
    out *= col
    out += 0.5
    return np.clip(out, 0, 255, out=out).astype(np.uint8)


def _unit(v: np.ndarray) -> np.ndarray:
    """Rows of ``v`` (N, 3) scaled to unit length (in place)."""
    v /= np.sqrt(np.einsum("ij,ij->i", v, v))[:, None]
    return v


_GLASS_BASE = np.array([0.16, 0.19, 0.24], np.float32)
_GLASS_TINT = np.array([0.08, 0.06, 0.04], np.float32)


def _facade(pts, normal, wall, par) -> np.ndarray:
    """Facade texture: window grid on walls (floor height par[:,0], spacing par[:,1], up to
    the roof height par[:,2]), a darker gravel tone on roofs. ``wall`` (N, 3) is changed in
    place and returned; each pattern is computed only on the pixels it applies to."""
    out = wall
    w = np.flatnonzero(np.abs(normal[:, 2]) < 0.5)
    if len(w):
        pw, nw, parw = _rows(pts, w), _rows(normal, w), _rows(par, w)
        u = pw[:, 0] * -nw[:, 1] + pw[:, 1] * nw[:, 0]
        z = pw[:, 2]
        fu = np.mod(u, parw[:, 1]) / parw[:, 1]
        fz = np.mod(z, parw[:, 0]) / parw[:, 0]
        win = np.flatnonzero((fu > 0.28) & (fu < 0.72) & (fz > 0.35) & (fz < 0.8) & (z > 1.5) & (z < parw[:, 2] - 0.8))
        _put_rows(out, w.take(win), parw[win, 3:4] * _GLASS_TINT + _GLASS_BASE)
    r = np.flatnonzero(normal[:, 2] > 0.5)
    if len(r):
        pr = _rows(pts, r)
        grain = 0.035 * _wave_noise(pr, 0.7, (0,)) + 0.02 * _wave_noise(pr, 3.1, (1,))
        _put_rows(out, r, _rows(out, r) * 0.62 + 0.12 + grain)
    return out


def render_views(scene: Scene, size: int, views=None, *, shade: bool = True) -> ContextViews:
    """Render ``views`` (default: all 605, in grid order) of a scene (``shade``: see
    :func:`render_view`)."""
    views = range(N_VIEWS) if views is None else views
    prep = _Prep(scene)
    out = [render_view(scene, v, size, prep, shade=shade) for v in views]
    return ContextViews(
        rgb=np.stack([o.rgb for o in out]),
        seg=np.stack([o.seg for o in out]),
        boxes=np.stack([o.box for o in out]).astype(np.int32),
        visible=np.array([o.visible for o in out], np.float32),
        categories=dict(scene.categories),
        target=scene.target,
    )


def render_context(context_id: int, *, size: int, seed: int) -> ContextViews:
    """All 605 views of context ``context_id`` at ``size`` px for a world seed (in memory)."""
    from .world import build_context

    return render_views(build_context(context_id, seed=seed), size)
