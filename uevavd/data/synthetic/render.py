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
kept for the scene (see :class:`ShadowMap`). Per-pixel shading works on index arrays
(``take`` / ``put``), and each texture only on the pixels it applies to.
Shading: Lambert with the sun (coloured) and a sky-weighted ambient term, procedural
textures for facades (windows), canopies (leaf clumps), glass and the ground map.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..grid import N_VIEWS, view_coords
from .ground import lookup
from .raycast import INF, ellipsoid_cast, hull_cast
from .scenes import TARGET_ID, Scene
from .shading import ShadowMap, shade_points
from .world import build_context


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


class PreparedScene:
    """Per-scene precomputation: float32 copies of the primitives, bounding spheres (frustum
    culling), real plane counts, lookup tables for shading, ellipsoid corner boxes."""

    def __init__(self, scene: Scene, shared: SharedShadows | None = None):
        p = scene.prims
        self._shared = shared
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

    def shadow_map(self, sun: np.ndarray, size: int) -> ShadowMap:
        """The scene's cached shadow map for crops of ``size`` px (cells ~0.8 of the pixel
        footprint at the nearest viewpoint, 60 m)."""
        key = (size, *np.round(sun, 9))
        if key not in self._shadow:
            cell = 0.8 * 60.0 / focal_px(size)
            if self._shared is None:
                self._shadow[key] = ShadowMap(self, sun, cell)
            else:
                self._shadow[key] = ShadowMap(self, sun, cell, cast="target",
                                               under=self._shared.others(self, key, sun, cell))
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


class SharedShadows:
    """The shadow map of everything but the target, cast once for the scenes that differ only
    in their target (the five of a ``train_605`` stage, :func:`world.with_target`): give it to
    each one's ``PreparedScene``, whose own map then casts the target alone over its tiles. The maps
    are the same bit for bit as each scene's own (see ``ShadowMap._tile``); a scene whose
    other primitives or sun differ from the first one's is refused."""

    def __init__(self) -> None:
        self._maps: dict[tuple, ShadowMap] = {}
        self._scene: list[np.ndarray] | None = None

    def others(self, prep: PreparedScene, key: tuple, sun: np.ndarray, cell: float) -> ShadowMap:
        p = prep.p
        h, e = p["h_inst"] != TARGET_ID, p["e_inst"] != TARGET_ID
        scene = [np.asarray(sun), p["h_planes"][h], p["h_verts"][h], p["e_centre"][e], p["e_radii"][e]]
        if self._scene is None:
            self._scene = scene
        elif not all(np.array_equal(a, b) for a, b in zip(self._scene, scene, strict=True)):
            raise ValueError("SharedShadows: this scene's sun or primitives other than the target differ from "
                             "those of the scenes sharing its shadows: give it a PreparedScene of its own")
        if key not in self._maps:
            self._maps[key] = ShadowMap(prep, sun, cell, cast="others")
        return self._maps[key]


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


def _pixel_dirs(size: int, basis: np.ndarray) -> np.ndarray:
    """(size, size, 3) float32 ray directions through the pixel centres (not normalised)."""
    c = np.arange(size, dtype=np.float64) + 0.5 - size / 2
    f, right, up = basis
    # the sum of a row term and a column term, in float64, rounded once to float32
    out = np.empty((size, size, 3), np.float32)
    np.add((focal_px(size) * f)[None, None] + c[None, :, None] * right, (-c)[:, None, None] * up, out=out)
    return out


def render_view(scene: Scene, view: int, size: int, prep: PreparedScene | None = None, *, cull: bool = True,
                exclude: tuple[int, ...] = (), shade: bool = True) -> View:
    """Render one viewpoint (grid index 0..604) of ``scene`` at ``size`` x ``size`` px.

    ``cull=False`` casts every primitive over the whole frame (the slow reference the
    benchmark compares against; the images are identical). ``exclude``: instance ids the
    camera does not see (they still cast their shadows). ``shade=False`` skips the colours
    (``rgb`` is then all zeros; segmentation, box and visible fraction are unchanged): the
    validity rule needs only the visible fractions."""
    prep = prep or PreparedScene(scene)
    v, hits = _cast_view(scene, view, size, prep, cull, exclude)
    return _shade(scene, prep, v, hits) if shade else v


def _shade(scene: Scene, prep: PreparedScene, v: View, hits: tuple) -> View:
    """``v`` with the colours of the ray hits ``hits`` (from :func:`_cast_view`)."""
    v.rgb = shade_points(scene, prep, *hits).reshape(v.rgb.shape)
    return v


def _cast_view(scene: Scene, view: int, size: int, prep: PreparedScene, cull: bool,
               exclude: tuple[int, ...]) -> tuple[View, tuple]:
    """The geometry of :func:`render_view`: the unshaded view, and the ray hits its colours
    are shaded from."""
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
    ttar = np.full((size, size), INF, np.float32)
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
        t, cand = hull_cast(h_ot[i, :k, None], den)  # (M,), (K, M)
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
        t = ellipsoid_cast(origin, dirs[y0:y1, x0:x1], p["e_centre"][i], p["e_radii"][i])
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
    v = View(rgb=np.zeros((size, size, 3), np.uint8), seg=seg, box=bx, visible=float(n_vis / full) if full else 0.0,
             occluders=occluders)
    return v, (pts, ground_rgb, h, e, pid_f, face_f)


def render_unoccluded_view(scene: Scene, view: int, size: int, prep: PreparedScene | None = None) -> View:
    """Render a view with every object that would hide part of the target left out of it
    (their shadows stay, as those of objects just outside the crop would): the target is
    fully visible, the rest of the scene as it is. One render when nothing hides the
    target; otherwise the objects drawn over it are left out and the view rendered again,
    until none is (an object behind a removed one may show up in its place). Only the last
    render is shaded."""
    prep = prep or PreparedScene(scene)
    v, hits = _cast_view(scene, view, size, prep, True, ())
    exclude: tuple[int, ...] = ()
    while v.occluders:
        exclude = tuple(sorted({*exclude, *v.occluders}))
        v, hits = _cast_view(scene, view, size, prep, True, exclude)
    return _shade(scene, prep, v, hits)


def render_views(scene: Scene, size: int, views=None, *, shade: bool = True) -> ContextViews:
    """Render ``views`` (default: all 605, in grid order) of a scene (``shade``: see
    :func:`render_view`)."""
    views = range(N_VIEWS) if views is None else views
    prep = PreparedScene(scene)
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
    return render_views(build_context(context_id, seed=seed), size)
