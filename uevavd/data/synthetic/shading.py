"""Shading of the synthetic world's renderer: the sun's shadow map (built tile by tile as
views need it) and Lambert shading with procedural textures (facades, glass, canopies)."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from .geometry import M_CABIN, M_CANOPY, M_FACADE
from .raycast import INF, ellipsoid_t, hull_t, put_rows, take_rows
from .scenes import TARGET_ID, Scene

if TYPE_CHECKING:  # pragma: no cover
    from .render import PreparedScene

class ShadowMap:
    """Lazily built, cached shadow map of a scene (the sun and the geometry are static).

    Frame (u, v, a) with a along the sun. The (u, v) plane is cut into tiles of ``TILE`` x
    ``TILE`` cells of ``cell`` metres; a tile holds, per cell, the highest a at which an
    orthographic ray from the sun enters a primitive, cast only against the primitives whose
    projected vertices overlap the tile. Tiles are computed the first time a view needs them
    and reused by every later view."""

    TILE = 128

    def __init__(self, prep: PreparedScene, sun: np.ndarray, cell: float, *, cast: str = "all",
                 under: ShadowMap | None = None):
        """``cast``: the primitives that cast shadows here, "all", "target" (the target's
        alone, on top of the tiles of ``under``, the map of the others) or "others"."""
        if cast not in ("all", "target", "others") or (under is None) == (cast == "target"):
            raise ValueError(f"cast={cast!r} with under={under!r}: a map of the target alone needs "
                             "the map of the others beneath it, and no other map has one")
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
        self.under = under
        self._tiles: dict[tuple[int, int], np.ndarray] = {}  # see tile()
        self.prims = []  # (kind, primitive indices, ulo, uhi, vlo, vhi)
        for kind, corners, inst in (("h", p["h_verts"], p["h_inst"]), ("e", prep.e_corners, p["e_inst"])):
            if len(corners):
                proj = corners @ self.frame.T
                lo, hi = proj.min(1), proj.max(1)
                index = np.arange(len(corners)) if cast == "all" else np.flatnonzero((inst == TARGET_ID) == (cast == "target"))
                self.prims.append((kind, index, lo[index, 0], hi[index, 0], lo[index, 1], hi[index, 1]))
        self.p = p

    def _tile(self, tu: int, tv: int) -> np.ndarray:
        span = self.TILE * self.cell
        u0, v0 = tu * span, tv * span
        cu = u0 + (np.arange(self.TILE) + 0.5) * self.cell
        cv = v0 + (np.arange(self.TILE) + 0.5) * self.cell
        top = 200.0  # sun rays start above everything (a < 200 m for every primitive)
        if self.under is None:
            depth = np.full((self.TILE, self.TILE), -INF, np.float32)
        else:  # a cell holds the maximum over primitives, so casting the rest on top of the
            # others' tile gives the depths of casting all, bit for bit (float32 rounding is monotonic)
            depth = self.under.tile(tu, tv).copy()
        fu, fv, sun = self.frame[0], self.frame[1], self.sun
        for kind, index, ulo, uhi, vlo, vhi in self.prims:
            hit = np.nonzero((ulo < u0 + span) & (uhi > u0) & (vlo < v0 + span) & (vhi > v0))[0]
            for k in hit:
                i = index[k]
                i0 = max(int((ulo[k] - u0) / self.cell), 0)
                i1 = min(int((uhi[k] - u0) / self.cell) + 2, self.TILE)
                j0 = max(int((vlo[k] - v0) / self.cell), 0)
                j1 = min(int((vhi[k] - v0) / self.cell) + 2, self.TILE)
                o = (cu[None, i0:i1, None] * fu + cv[j0:j1, None, None] * fv + top * sun).reshape(-1, 3)
                if kind == "h":
                    pl = self.p["h_planes"][i].astype(np.float64)
                    # + 0.0: a hull's padding planes (0 . p <= 1) give -(0 . sun) = -0.0, which
                    # hull_t would read as a plane the ray leaves at -inf, so no sun ray would hit
                    # any hull (world versions <= 4 cast only the ellipsoids' shadows)
                    den = -(pl[:, :3] @ sun)[:, None] + 0.0
                    t = hull_t(pl[:, 3, None] - pl[:, :3] @ o.T, den, 0)
                else:
                    t = ellipsoid_t(o, -sun, self.p["e_centre"][i], self.p["e_radii"][i])
                sub = depth[j0:j1, i0:i1]
                np.maximum(sub, (top - t).reshape(sub.shape), out=sub)
        return depth

    def tile(self, tu: int, tv: int) -> np.ndarray:
        """Tile (tu, tv), computed once and kept (read-only): the tiles a map beneath others
        gives them (``under``)."""
        if (tu, tv) not in self._tiles:
            self._tiles[tu, tv] = self._tile(tu, tv)
        return self._tiles[tu, tv]

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


def shade_points(scene: Scene, prep: PreparedScene, pts, ground_rgb, h, e, pid, face) -> np.ndarray:
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
        nh = take_rows(prep.h_normals, hp * prep.h_k + face.take(h))
        put_rows(normal, h, nh)
        c = take_rows(p["h_rgb"], hp)
        mat = p["h_mat"].take(hp)
        cab = np.flatnonzero((mat == M_CABIN) & (nh[:, 2] < 0.9))  # glass
        if len(cab):
            put_rows(c, cab, take_rows(prep.h_glass, hp.take(cab)))
        fac = np.flatnonzero(mat == M_FACADE)
        if len(fac):
            put_rows(c, fac, _facade(take_rows(pts, h.take(fac)), take_rows(nh, fac), take_rows(c, fac), take_rows(p["h_par"], hp.take(fac))))
        put_rows(col, h, c)
    if len(e):
        ep = pid.take(e)
        pe = take_rows(pts, e)
        n = (pe - take_rows(prep.e_c32, ep)) * take_rows(prep.e_inv_r2, ep)  # gradient of the ellipsoid's equation
        c = take_rows(p["e_rgb"], ep)
        can = np.flatnonzero(p["e_mat"].take(ep) == M_CANOPY)
        if len(can) == len(e):  # woodland: every ellipsoid is a canopy
            wn = _wave_noise(pe, 1.6)
            n = _unit(n) + 0.55 * wn
            c *= 1.0 + 0.18 * wn[:, :1]
        elif len(can):
            wn = _wave_noise(take_rows(pe, can), 1.6)
            put_rows(n, can, _unit(take_rows(n, can)) + 0.55 * wn)
            put_rows(c, can, take_rows(c, can) * (1.0 + 0.18 * wn[:, :1]))
        put_rows(normal, e, _unit(n))
        put_rows(col, e, c)
        bias.put(e, 0.6)
    lam = rows_dot_f32(normal, scene.sun_dir.astype(np.float32))
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


def rows_dot_f32(rows: np.ndarray, v: np.ndarray) -> np.ndarray:
    """``rows @ v`` for float32 rows (N, 3) and a float32 3-vector, computed without BLAS, the
    same bits on every machine.

    numpy's ``@`` here calls OpenBLAS's sgemv, whose kernel depends on the CPU; the world's
    records (the zoo's scene digests) were rendered with its AVX-512 kernel (``SkylakeX``),
    while e.g. an AMD EPYC gets the AVX2 one (``Haswell``), which sums ``(r0 v0 + r1 v1) +
    r2 v2`` unfused: about one colour value in 10^6 came out one level apart, and 17 of the
    quick world's 30 context scenes hashed differently. This function is that AVX-512
    kernel's arithmetic, measured against it on every N from 2 to 600 (numpy hands a single
    row to another routine), around its switch at 16,384 rows and on 2 M random rows
    (OpenBLAS 0.3.31; ``tests/data/test_blas_independence.py``), in exactly rounded float64
    operations: for N <= 16,384, blocks of 16 and then one of 8 rows compute
    ``fma(r2, v2, fma(r1, v1, r0 v0))``, a following block of 4 and a last single row
    ``fma(r2, v2, fma(r0, v0, r1 v1))``, a pair between them the unfused sum; above 16,384
    rows every row takes the second form."""
    r = np.ascontiguousarray(rows, np.float32)
    v = np.asarray(v, np.float32)
    n = len(r)

    def fused(i: int, j: int, rs: np.ndarray) -> np.ndarray:  # fma(r2, v2, fma(rj, vj, ri vi))
        return _fma_f32(rs[:, 2], v[2], _fma_f32(rs[:, j], v[j], rs[:, i] * v[i]))

    if n > _SGEMV_SPLIT:
        return fused(1, 0, r)
    out = fused(0, 1, r)
    m = n - n % 16 + (8 if n % 16 >= 8 else 0)  # the rows the 16- and 8-row blocks cover
    if n - m >= 4:
        out[m:m + 4] = fused(1, 0, r[m:m + 4])
        m += 4
    if n - m >= 2:
        pair = r[m:m + 2]
        out[m:m + 2] = (pair[:, 0] * v[0] + pair[:, 1] * v[1]) + pair[:, 2] * v[2]
        m += 2
    if n - m == 1:
        out[m:] = fused(1, 0, r[m:])
    return out


#: Above this many rows the AVX-512 sgemv takes its other path (see rows_dot_f32).
_SGEMV_SPLIT = 16384


def _fma_f32(x: np.ndarray, y: np.float32, z: np.ndarray) -> np.ndarray:
    """float32 ``x * y + z`` rounded once, as a fused multiply-add does: the product of two
    float32s is exact in float64, and the float64 sum, rounded to float32, is the fused result
    except where that sum fell exactly halfway between two float32s (its 29 dropped bits
    ``1 0...0``; or in float32's subnormal range) while the exact sum was not: there, the
    float64 sum's error (TwoSum, exact) decides the rounding."""
    p = x.astype(np.float64) * np.float64(y)
    z64 = z.astype(np.float64)
    s = p + z64
    out = s.astype(np.float32)
    halfway = ((s.view(np.uint64) & np.uint64(0x1FFFFFFF)) == np.uint64(0x10000000)) | (np.abs(s) < 2.0**-125)
    i = np.flatnonzero(halfway)
    if len(i):
        pi, zi, si, oi = p[i], z64[i], s[i], out[i]
        back = si - pi
        err = (pi - (si - back)) + (zi - back)  # si + err == pi + zi exactly
        below = si - oi.astype(np.float64)  # exact: oi is si rounded to float32
        other = np.nextafter(oi, np.where(below > 0, np.float32(np.inf), np.float32(-np.inf)))
        tie = (err != 0) & (below != 0) & (2 * np.abs(below) == np.abs(other.astype(np.float64) - oi))
        away = tie & (np.sign(err) == np.sign(below))  # the exact sum lies past the midpoint
        out[i[away]] = other[away]
    return out


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
        pw, nw, parw = take_rows(pts, w), take_rows(normal, w), take_rows(par, w)
        u = pw[:, 0] * -nw[:, 1] + pw[:, 1] * nw[:, 0]
        z = pw[:, 2]
        fu = np.mod(u, parw[:, 1]) / parw[:, 1]
        fz = np.mod(z, parw[:, 0]) / parw[:, 0]
        win = np.flatnonzero((fu > 0.28) & (fu < 0.72) & (fz > 0.35) & (fz < 0.8) & (z > 1.5) & (z < parw[:, 2] - 0.8))
        put_rows(out, w.take(win), parw[win, 3:4] * _GLASS_TINT + _GLASS_BASE)
    r = np.flatnonzero(normal[:, 2] > 0.5)
    if len(r):
        pr = take_rows(pts, r)
        grain = 0.035 * _wave_noise(pr, 0.7, (0,)) + 0.02 * _wave_noise(pr, 3.1, (1,))
        put_rows(out, r, take_rows(out, r) * 0.62 + 0.12 + grain)
    return out
