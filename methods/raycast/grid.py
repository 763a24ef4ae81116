"""A voxel occupancy grid with a max-pooled pyramid, and ray traversal over it (numba).

Level 0 holds ``voxel`` sized cells over a box (the ROI by default); level ``l`` cells are
``2**l`` voxels wide and occupied when any voxel inside is. Rays skip empty space on the
coarsest empty level (exact: a cell is only skipped when nothing inside it is occupied), so
a ray costs about as many steps as the levels it crosses, not the voxels.

Cone traversal (the sparsity policy of ``raycast-voxel``): at a point at distance ``r`` from
the cone centre a ray stops at the first occupied cell of the smallest level whose cell size
is at least ``r * cone`` (``cone`` in radians, for example twice the beam spacing), capped at
``max_level``. With the centre at the past sensor, the ray is as thick as the gaps between
the past beams there and cannot slip between them. A hit on a coarse cell is refined with a fine (level 0) traversal inside that cell;
when the fine ray still slips through, the middle of the ray's segment in the coarse cell is
the hit.

Depth in a hit voxel (``cast(surface=True)``, what the methods use): every occupied voxel has
a surface, the plane through the mean of its points whose normal is that of the flat points
of its cell at the coarsest level up to ``PLANE_LEVELS`` (1.6 m) that has them (least-variance
direction, closed-form 3x3 eigenvectors: ``sym3_smallest``; "flat": at least 3 points spread
over 2 cm, at most 5 cm thick); a wide patch gives a steadier normal than one voxel's few
centimetres. The ray ends where it crosses that plane, not before its entry into the voxel
and at most ``FOLLOW_RANGE`` past it (``_surface_depth``): a grazing ray that entered the
ground's voxel through its top face meets the ground further on, also across the unobserved
voxels between far beams. Voxels without a surface, and longer follows, answer the projection
of the mean of the voxel's points on the ray, clamped to the ray's segment in the voxel
(``surface=False`` everywhere: the former rule).

Grid phase (``anchor_z``): the grid may start below the box so that a face of every level
passes through a given height. ``raycast-voxel`` puts one half a voxel above the ground under
the sensor, so that the ground lies mid-voxel and its noise does not speckle the cells above
it (which would make rays coming down to it take small steps). The surfaces make the depth
independent of the phase.

Storage: the pyramid is one bit per cell, and a hit voxel's points are found through the
first key of its (x, y) column. ``_cast`` is serial (nogil): the caller shares rays out over
threads.

Empty-box jumps: ``_slab_field`` gives every level-1 cell and every top-level cell the
chessboard distance ``r`` in (x, y) to the nearest occupied cell of its z slice; the
``2r - 1`` x ``2r - 1`` x 1 box of cells around it is then empty, and a skip of an empty cell
of that level jumps to the box's exit instead (at level 1 only while the cone needs at most
level 1 up to there, so that no coarser occupied cell the plain traversal would stop at is
jumped over). Where faces nearly meet, a grazing hit's entry point can move by less than the
10 um step past a face.

Exactness of the fast steps: the cone's level comes from comparing ``t`` with the ranges where
it doubles (the distance to the centre only within 1e-7 of one), the cell from a product with
``1 / vs`` (the division only within 1e-9 of a face, where the two could round apart), so the
traversal visits the same cells, and gives the same depths, as the plain arithmetic. The
march (``_march``) is inlined into ``_cast``'s per-ray loop (a compiled call per ray that
takes arrays updates their shared reference counts, which threads contend on). Measurements, and what was
tried and left out: docs/journal/performance-tuning-2026-11.md.
"""

from __future__ import annotations

import copy

import numba as nb
import numpy as np

from pcfbench.protocol import ROI
from pcfbench.boxes import Box

#: the coarsest level of an empty-cell skip that may be stretched by the slab field
FIELD_MAX_STEP = 1


@nb.njit(cache=True)
def _voxel_keys(points, lo, vs, nx, ny, nz):
    n = points.shape[0]
    keys = np.full(n, -1, np.int64)
    for i in range(n):
        a = int(np.floor((points[i, 0] - lo[0]) / vs))
        b = int(np.floor((points[i, 1] - lo[1]) / vs))
        c = int(np.floor((points[i, 2] - lo[2]) / vs))
        if 0 <= a < nx and 0 <= b < ny and 0 <= c < nz:
            keys[i] = (a * ny + b) * nz + c
    return keys


@nb.njit(cache=True)
def _fill(occ, offs, dims, keys):
    K = offs.shape[0] - 1
    ny0 = dims[0, 1]
    nz0 = dims[0, 2]
    for k in keys:
        a = k // (ny0 * nz0)
        b = (k // nz0) % ny0
        c = k % nz0
        for lvl in range(K + 1):
            bit = offs[lvl] + ((a >> lvl) * dims[lvl, 1] + (b >> lvl)) * dims[lvl, 2] + (c >> lvl)
            occ[bit >> 6] |= np.uint64(1) << np.uint64(bit & 63)


#: the moments of a voxel's points (``_moments``): count, sums of x, y, z, and of xx, xy, xz, yy, yz, zz
MOMENTS = 10
#: a surface needs at least this many points ...
PLANE_MIN_POINTS = 3
#: ... spread at least this much (m, standard deviation) along its second axis ...
PLANE_MIN_SPREAD = 0.02
#: ... and a thickness (variance along the normal) at most this fraction of that spread's variance ...
PLANE_MAX_FLATNESS = 0.25
#: ... and at most this (m, standard deviation along the normal)
PLANE_MAX_THICKNESS = 0.05
#: a surface's normal comes from the coarsest flat cell around its voxel up to this level (1.6 m)
PLANE_LEVELS = 3
#: a hit voxel's surface is followed at most this far (m) past the ray's entry (see ``_surface_depth``)
FOLLOW_RANGE = 3.0


@nb.njit(cache=True)
def _moments(points, slot, k):
    """Per occupied voxel (``slot`` of each point, -1 outside), the ``MOMENTS`` sums of its points."""
    mom = np.zeros((k, MOMENTS))
    for i in range(points.shape[0]):
        s = slot[i]
        if s < 0:
            continue
        x, y, z = points[i, 0], points[i, 1], points[i, 2]
        m = mom[s]
        m[0] += 1.0
        m[1] += x
        m[2] += y
        m[3] += z
        m[4] += x * x
        m[5] += x * y
        m[6] += x * z
        m[7] += y * y
        m[8] += y * z
        m[9] += z * z
    return mom


@nb.njit(inline="always")
def _cross_norm2(a0, a1, a2, b0, b1, b2):
    c0 = a1 * b2 - a2 * b1
    c1 = a2 * b0 - a0 * b2
    c2 = a0 * b1 - a1 * b0
    return c0, c1, c2, c0 * c0 + c1 * c1 + c2 * c2


@nb.njit(cache=True)
def sym3_smallest(a00, a01, a02, a11, a12, a22):
    """The two smallest eigenvalues (ascending) of the symmetric 3x3 matrix ``a`` and a unit
    eigenvector of the smallest: closed-form eigenvalues (the trigonometric solution of the
    characteristic cubic), the vector as the longest cross product of two rows of ``a - l I``
    (well defined when the smallest eigenvalue is simple)."""
    p1 = a01 * a01 + a02 * a02 + a12 * a12
    q = (a00 + a11 + a22) / 3.0
    p2 = (a00 - q) ** 2 + (a11 - q) ** 2 + (a22 - q) ** 2 + 2.0 * p1
    if p2 <= 0.0:
        return q, q, 0.0, 0.0, 1.0  # a multiple of the identity: any vector
    p = np.sqrt(p2 / 6.0)
    b00 = (a00 - q) / p
    b11 = (a11 - q) / p
    b22 = (a22 - q) / p
    b01 = a01 / p
    b02 = a02 / p
    b12 = a12 / p
    r = 0.5 * (b00 * (b11 * b22 - b12 * b12) - b01 * (b01 * b22 - b12 * b02) + b02 * (b01 * b12 - b11 * b02))
    r = min(max(r, -1.0), 1.0)
    phi = np.arccos(r) / 3.0
    l_max = q + 2.0 * p * np.cos(phi)
    l_min = q + 2.0 * p * np.cos(phi + 2.0 * np.pi / 3.0)
    l_mid = 3.0 * q - l_max - l_min
    r00 = a00 - l_min
    r11 = a11 - l_min
    r22 = a22 - l_min
    x0, x1, x2, nx = _cross_norm2(r00, a01, a02, a01, r11, a12)
    y0, y1, y2, ny = _cross_norm2(r00, a01, a02, a02, a12, r22)
    z0, z1, z2, nz = _cross_norm2(a01, r11, a12, a02, a12, r22)
    if ny > nx and ny >= nz:
        x0, x1, x2, nx = y0, y1, y2, ny
    elif nz > nx:
        x0, x1, x2, nx = z0, z1, z2, nz
    if nx <= 0.0:
        return l_min, l_mid, 0.0, 0.0, 1.0
    w = 1.0 / np.sqrt(nx)
    return l_min, min(l_mid, l_max), x0 * w, x1 * w, x2 * w


@nb.njit(cache=True)
def _plane(m):
    """Whether the points with moments ``m`` are flat (see ``PLANE_*``: enough of them, spread
    out, thin), and the unit normal of their least-variance direction."""
    n = m[0]
    if n < PLANE_MIN_POINTS:
        return False, 0.0, 0.0, 0.0
    mx, my, mz = m[1] / n, m[2] / n, m[3] / n
    l_min, l_mid, nx, ny, nz = sym3_smallest(m[4] / n - mx * mx, m[5] / n - mx * my, m[6] / n - mx * mz,
                                             m[7] / n - my * my, m[8] / n - my * mz, m[9] / n - mz * mz)
    flat = l_mid > PLANE_MIN_SPREAD**2 and l_min < PLANE_MAX_FLATNESS * l_mid and l_min < PLANE_MAX_THICKNESS**2
    return flat, nx, ny, nz


@nb.njit(cache=True)
def _planes(mom, parents):
    """Per occupied voxel, its surface: the plane through the mean of its points whose normal
    is that of the flat points of its cell at the coarsest level that has them, over the voxel
    itself and the levels whose cell indices (0..P-1 per voxel) are the rows of ``parents``
    (finest first). A wide patch of ground gives a steadier normal than the few centimetres of
    one voxel's points, and the voxel's own mean keeps the plane where its points are. Rows of
    the unit normal ``n`` and the offset ``n . mean``; zeros where no level is flat."""
    k = mom.shape[0]
    out = np.zeros((k, 4))
    found = np.zeros(k, np.bool_)
    for lvl in range(parents.shape[0], -1, -1):
        if lvl == 0:
            cmom = mom
            cell = np.arange(k)
        else:
            cell = parents[lvl - 1]
            ncell = 0
            for i in range(k):
                ncell = max(ncell, cell[i] + 1)
            cmom = np.zeros((ncell, MOMENTS))
            for i in range(k):
                cmom[cell[i]] += mom[i]
        ok = np.zeros(cmom.shape[0], np.bool_)
        normals = np.zeros((cmom.shape[0], 3))
        for j in range(cmom.shape[0]):
            ok[j], normals[j, 0], normals[j, 1], normals[j, 2] = _plane(cmom[j])
        for i in range(k):
            if not found[i] and ok[cell[i]]:
                found[i] = True
                n = mom[i, 0]
                out[i, :3] = normals[cell[i]]
                out[i, 3] = (out[i, 0] * mom[i, 1] + out[i, 1] * mom[i, 2] + out[i, 2] * mom[i, 3]) / n
    return out


@nb.njit(inline="always")
def _occupied(occ, bit):
    """Whether the cell at bit ``bit`` of the packed pyramid is occupied."""
    return (occ[bit >> 6] >> np.uint64(bit & 63)) & np.uint64(1) != 0


@nb.njit(inline="always")
def _exit(o, iv, lo, size, i, t_exit):
    """The ray's exit parameter through the planes of cell ``i`` along one axis (min with ``t_exit``)."""
    if iv > 0:
        return min(t_exit, (lo + (i + 1) * size - o) * iv)
    if iv < 0:
        return min(t_exit, (lo + i * size - o) * iv)
    return t_exit


@nb.njit(inline="always")
def _box_exit(o, iv, lo, size, i, r, t_exit):
    """``_exit`` of the run of cells ``i - r + 1 .. i + r - 1`` along one axis."""
    if iv > 0:
        return min(t_exit, (lo + (i + r) * size - o) * iv)
    if iv < 0:
        return min(t_exit, (lo + (i - r + 1) * size - o) * iv)
    return t_exit


@nb.njit(cache=True)
def _slab_field(occ, off1, n1x, n1y, n1z):
    """Per level-1 cell, its chessboard distance in (x, y) to the nearest occupied level-1 cell
    of the same z slice (0: occupied), capped at 255: the ``2r - 1`` x ``2r - 1`` x 1 box of
    level-1 cells around a cell at distance ``r`` is empty. Outside the grid counts as empty.
    Two raster passes with the 8-neighbourhood (exact for the chessboard distance), on an
    array with a one-cell border of "far" so that the inner loop over z has no branches."""
    big = 1 << 20
    f = np.full((n1x + 2, n1y + 2, n1z), big, np.int32)
    for i in range(n1x):
        for j in range(n1y):
            for k in range(n1z):
                if _occupied(occ, off1 + (i * n1y + j) * n1z + k):
                    f[i + 1, j + 1, k] = 0
    for i in range(1, n1x + 1):
        for j in range(1, n1y + 1):
            for k in range(n1z):
                f[i, j, k] = min(f[i, j, k], min(min(f[i - 1, j - 1, k], f[i - 1, j, k]), min(f[i - 1, j + 1, k], f[i, j - 1, k])) + 1)
    for i in range(n1x, 0, -1):
        for j in range(n1y, 0, -1):
            for k in range(n1z):
                f[i, j, k] = min(f[i, j, k], min(min(f[i + 1, j + 1, k], f[i + 1, j, k]), min(f[i + 1, j - 1, k], f[i, j + 1, k])) + 1)
    out = np.empty(n1x * n1y * n1z, np.uint8)
    for i in range(n1x):
        for j in range(n1y):
            for k in range(n1z):
                out[(i * n1y + j) * n1z + k] = min(f[i + 1, j + 1, k], 255)
    return out


@nb.njit(inline="always")
def _cell_exit(o0, o1, o2, i0, i1, i2, l0, l1, l2, size, a, b, c, t):
    """The ray's exit from the cell (a, b, c) of edge ``size``, at least ``t``: ``_exit`` on
    each axis, written with selects instead of branches on the direction's signs."""
    e0 = (l0 + (a + (1 if i0 > 0 else 0)) * size - o0) * i0
    e1 = (l1 + (b + (1 if i1 > 0 else 0)) * size - o1) * i1
    e2 = (l2 + (c + (1 if i2 > 0 else 0)) * size - o2) * i2
    te = e0 if i0 != 0.0 else np.inf
    te = min(te, e1) if i1 != 0.0 else te
    te = min(te, e2) if i2 != 0.0 else te
    return max(te, t)


@nb.njit(inline="always")
def _need(x, y, z, c0, c1, c2, vs, cone, max_level):
    """The cone's level at (x, y, z): the smallest whose cell is at least as wide as the cone there."""
    w = np.sqrt((x - c0) ** 2 + (y - c1) ** 2 + (z - c2) ** 2) * cone
    need = 0
    while need < max_level and vs * (1 << need) < w:
        need += 1
    return need


@nb.njit(inline="always")  # inlined: see the module docstring
def _march(o0, o1, o2, d0, d1, d2, i0, i1, i2, t, t1, occ, offs, dims, lo, vs, cone, max_level, c0, c1, c2, thr0,
           field, ftop):
    """First occupied cell along the ray ``o + t d`` (``i``: the inverse direction, 0 where
    ``d`` is) in [t, t1). Returns (t_entry, t_exit, level, key) with t_entry < 0 when nothing
    is hit; ``key`` is the level-0 key (only for level-0 hits).

    ``thr0 > 0`` says the cone centre ``c`` is the ray's origin, so that the cone is ``vs``
    wide at ``t = thr0`` and ``vs * 2**l`` at ``thr0 * 2**l``: the cone's level then comes
    from comparing ``t`` with those ranges, and only within a relative 1e-7 of one (where
    rounding could decide) from the distance to the centre as before (``_need``), so both give
    the same level. ``thr0 = 0``: always ``_need``.

    ``field`` (see ``_slab_field``) lets a skip of an empty cell of level >= 1 jump further,
    to the exit of the empty box of level-1 cells around it, when the cone needs at most
    level 1 up to there (then every cell the old steps inside the box met was empty too)."""
    K = offs.shape[0] - 1
    nx0 = dims[0, 0]
    ny0 = dims[0, 1]
    nz0 = dims[0, 2]
    eps = 1e-5
    tol = 1e-4
    top = K
    l0, l1, l2 = lo[0], lo[1], lo[2]
    ivs = 1.0 / vs
    # |(x - lo) * ivs - (x - lo) / vs| < 4e-16 * (n + 1) inside the grid: a wide margin on that
    band = 1e-12 * (max(nx0, max(ny0, nz0)) + 2)
    half = 0.5 - band
    # whether the segment [t, t1] stays inside the grid by a margin far above the rounding of
    # the positions along it: then no step leaves the grid, and the checks are left out
    inside = True
    for tt in (t, t1):
        for q, n in (((o0 + d0 * tt - l0) * ivs, nx0), ((o1 + d1 * tt - l1) * ivs, ny0), ((o2 + d2 * tt - l2) * ivs, nz0)):
            if not (q > -tol + 1e-6 and q < n + tol - 1e-6):
                inside = False
    # the level the cone needs (``nd``) past the last threshold passed for sure, and the band
    # around the next threshold ``tn`` where the distance decides
    nd = 0
    tn = thr0
    tband = tn * 1e-7 + 1e-9
    while t < t1:
        x = o0 + d0 * t
        y = o1 + d1 * t
        z = o2 + d2 * t
        # the cell as ``(x - lo) / vs`` gives it (as _voxel_keys computes it, so that a ray along a
        # face agrees), from a product with ``1 / vs`` where that cannot differ: the two differ
        # by a few ulp, so only within ``band`` of a face (or off the ``inside`` segment) the
        # division decides, and checks the grid's bounds
        qa = (x - l0) * ivs
        qb = (y - l1) * ivs
        qc = (z - l2) * ivs
        ka = np.floor(qa)
        kb = np.floor(qb)
        kc = np.floor(qc)
        if inside and abs(qa - ka - 0.5) < half and abs(qb - kb - 0.5) < half and abs(qc - kc - 0.5) < half:
            a = min(max(int(ka), 0), nx0 - 1)
            b = min(max(int(kb), 0), ny0 - 1)
            c = min(max(int(kc), 0), nz0 - 1)
        else:
            fa = (x - l0) / vs
            fb = (y - l1) / vs
            fc = (z - l2) / vs
            if fa < -tol or fb < -tol or fc < -tol or fa > nx0 + tol or fb > ny0 + tol or fc > nz0 + tol:
                break  # the ray has left the grid
            a = min(max(int(np.floor(fa)), 0), nx0 - 1)  # rounding at the faces
            b = min(max(int(np.floor(fb)), 0), ny0 - 1)
            c = min(max(int(np.floor(fc)), 0), nz0 - 1)
        need = 0
        if cone > 0.0:
            # as wide as the beam gaps where the past sensor (at ``center``) saw this place
            if thr0 > 0.0:
                while nd < max_level and t > tn + tband:
                    nd += 1
                    tn = thr0 * (1 << nd)
                    tband = tn * 1e-7 + 1e-9
                need = nd
                if nd < max_level and t >= tn - tband:
                    need = _need(x, y, z, c0, c1, c2, vs, cone, max_level)
            else:
                need = _need(x, y, z, c0, c1, c2, vs, cone, max_level)
        # start at the level of the last skip and climb while the parent is empty (the climb
        # from one level above, which read that parent and then the cell again, ends alike)
        lvl = top
        while lvl < K and not _occupied(occ, offs[lvl + 1] + (((a >> (lvl + 1)) * dims[lvl + 1, 1] + (b >> (lvl + 1))) * dims[lvl + 1, 2] + (c >> (lvl + 1)))):
            lvl += 1
        if lvl < need:
            lvl = need
        skipped = False
        while lvl >= need:
            ia = a >> lvl
            ib = b >> lvl
            ic = c >> lvl
            if not _occupied(occ, offs[lvl] + (ia * dims[lvl, 1] + ib) * dims[lvl, 2] + ic):
                tn_ = _cell_exit(o0, o1, o2, i0, i1, i2, l0, l1, l2, vs * (1 << lvl), ia, ib, ic, t)
                if lvl == K and K >= 2:
                    # the top level: any cone fits (need <= max_level <= K)
                    r = np.int64(ftop[(ia * dims[K, 1] + ib) * dims[K, 2] + ic])
                    if r >= 2:
                        tb = _box_exit(o0, i0, l0, vs * (1 << lvl), ia, r, np.inf)
                        tb = _box_exit(o1, i1, l1, vs * (1 << lvl), ib, r, tb)
                        tb = _box_exit(o2, i2, l2, vs * (1 << lvl), ic, 1, tb)
                        tn_ = max(tn_, tb)
                elif lvl >= 1 and lvl <= FIELD_MAX_STEP and need <= 1:
                    fa1 = a >> 1
                    fb1 = b >> 1
                    fc1 = c >> 1
                    r = np.int64(field[(fa1 * dims[1, 1] + fb1) * dims[1, 2] + fc1])
                    if r >= 2:
                        tb = _box_exit(o0, i0, l0, 2.0 * vs, fa1, r, np.inf)
                        tb = _box_exit(o1, i1, l1, 2.0 * vs, fb1, r, tb)
                        tb = _box_exit(o2, i2, l2, 2.0 * vs, fc1, 1, tb)
                        if tb > tn_:
                            ok = True
                            if cone > 0.0 and max_level >= 2:
                                # the cone needs at most level 1 at the box's exit
                                tt = tb + eps
                                t2 = 2.0 * thr0
                                b2 = t2 * 1e-7 + 1e-9
                                if thr0 > 0.0 and tt < t2 - b2:
                                    ok = True
                                elif thr0 > 0.0 and tt > t2 + b2:
                                    ok = False
                                else:
                                    w = np.sqrt((o0 + d0 * tt - c0) ** 2 + (o1 + d1 * tt - c1) ** 2 + (o2 + d2 * tt - c2) ** 2) * cone
                                    ok = not (vs * 2 < w)
                            if ok:
                                tn_ = tb
                t = tn_ + eps
                top = lvl
                skipped = True
                break
            lvl -= 1
        if not skipped:
            ia = a >> need
            ib = b >> need
            ic = c >> need
            te = _cell_exit(o0, o1, o2, i0, i1, i2, l0, l1, l2, vs * (1 << need), ia, ib, ic, t)
            return t, min(te, t1), need, (a * ny0 + b) * nz0 + c
    return -1.0, -1.0, 0, -1


@nb.njit(inline="always")
def _slot(col_start, ukeys, key, nz0):
    """Index of ``key`` in the sorted occupied keys, -1 if absent: a column (x, y) of the grid
    holds consecutive keys, so a short scan from the column's first key finds it."""
    col = key // nz0
    for i in range(col_start[col], col_start[col + 1]):
        if ukeys[i] == key:
            return i
    return -1


@nb.njit(cache=True)
def _column_starts(ukeys, ncols, nz0):
    """First index in ``ukeys`` of each (x, y) column's keys (``ncols + 1`` entries)."""
    starts = np.zeros(ncols + 1, np.int32)
    for k in ukeys:
        starts[k // nz0 + 1] += 1
    for c in range(ncols):
        starts[c + 1] += starts[c]
    return starts


@nb.njit(inline="always")
def _inverse(d):
    return 1.0 / d if d != 0.0 else 0.0


@nb.njit(inline="always")
def _slab(o, d, lo, hi, t_enter, t_exit):
    """One slab of ``pcfbench.boxes.ray_box_interval`` for one ray (the same arithmetic)."""
    if d == 0.0:  # parallel to the slab: inside it or never
        if lo <= o <= hi:
            return t_enter, t_exit
        return max(t_enter, np.inf), min(t_exit, -np.inf)
    ta = (lo - o) / d
    tb = (hi - o) / d
    return max(t_enter, min(ta, tb)), min(t_exit, max(ta, tb))


@nb.njit(nogil=True, cache=True)
def _cast(origin, dirs, box_lo, box_hi, occ, offs, dims, lo, vs, cone, max_level, ukeys, col_start, means, center, field,
          ftop, planes, surface):
    """First-hit depth per ray of ``dirs`` from ``origin``, within ``box`` (``ray_box_interval``)."""
    m = dirs.shape[0]
    out = np.full(m, np.nan)
    o0, o1, o2 = origin[0], origin[1], origin[2]
    c0, c1, c2 = center[0], center[1], center[2]
    linear = c0 == o0 and c1 == o1 and c2 == o2
    nz0 = dims[0, 2]
    for j in range(m):
        d0, d1, d2 = dirs[j, 0], dirs[j, 1], dirs[j, 2]
        t0, t1 = _slab(o0, d0, box_lo[0], box_hi[0], 0.0, np.inf)
        t0, t1 = _slab(o1, d1, box_lo[1], box_hi[1], t0, t1)
        t0, t1 = _slab(o2, d2, box_lo[2], box_hi[2], t0, t1)
        if not t0 < t1:
            continue
        i0, i1, i2 = _inverse(d0), _inverse(d1), _inverse(d2)
        thr0 = 0.0
        if linear and cone > 0.0:
            thr0 = vs / (cone * np.sqrt(d0 * d0 + d1 * d1 + d2 * d2))
        te, tx, lvl, key = _march(o0, o1, o2, d0, d1, d2, i0, i1, i2, t0, t1, occ, offs, dims, lo, vs, cone, max_level,
                                  c0, c1, c2, thr0, field, ftop)
        if te < 0:
            continue
        if lvl > 0:  # refine a coarse (cone) hit inside its cell
            fe, fx, _, fkey = _march(o0, o1, o2, d0, d1, d2, i0, i1, i2, te, tx, occ, offs, dims, lo, vs, 0.0, 0,
                                     c0, c1, c2, 0.0, field, ftop)
            if fe < 0:
                out[j] = 0.5 * (te + tx)
                continue
            te, tx, key = fe, fx, fkey
        s = _slot(col_start, ukeys, key, nz0)
        if surface:
            out[j] = _surface_depth(o0, o1, o2, d0, d1, d2, te, tx, s, means, planes)
        else:
            out[j] = _mean_depth(o0, o1, o2, d0, d1, d2, te, tx, s, means)
    return out


@nb.njit(inline="always")
def _mean_depth(o0, o1, o2, d0, d1, d2, te, tx, s, means):
    """The depth of a hit on the voxel at slot ``s`` (segment ``te..tx``): the projection of its
    points' mean on the ray, clamped to the segment (``te`` without the voxel's points)."""
    if s < 0:
        return te
    p = (means[s, 0] - o0) * d0 + (means[s, 1] - o1) * d1 + (means[s, 2] - o2) * d2
    return min(max(p, te), tx)


@nb.njit(inline="always")
def _surface_depth(o0, o1, o2, d0, d1, d2, te, tx, s, means, planes):
    """The depth of a hit on the voxel at slot ``s`` (the ray's segment in it: ``te..tx``) on
    the voxel's surface (a row of ``planes``: unit normal and offset, see ``_planes``): where
    the ray crosses it, but not before the entry, and not more than ``FOLLOW_RANGE`` past it.
    A crossing beyond the voxel's exit is that of a grazing ray that entered the voxel above
    its surface (through the top face of the ground's voxel): the ground goes on under the ray,
    also across unobserved voxels between far beams. Without a surface (or with one along the
    ray), and for a crossing farther on: ``_mean_depth``."""
    if s < 0:
        return te
    den = planes[s, 0] * d0 + planes[s, 1] * d1 + planes[s, 2] * d2
    if den != 0.0:
        ts = (planes[s, 3] - (planes[s, 0] * o0 + planes[s, 1] * o1 + planes[s, 2] * o2)) / den
        if ts <= te + FOLLOW_RANGE:
            return max(ts, te)
    return _mean_depth(o0, o1, o2, d0, d1, d2, te, tx, s, means)


@nb.njit(cache=True)
def _carve(origins, points, t_end, occ, offs, dims, lo, vs, ukeys, col_start, free, field, ftop):
    """Count, for every occupied voxel, the past rays that passed through it before ``t_end``."""
    for i in range(points.shape[0]):
        o = origins[i]
        d = points[i] - o
        r = np.sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2])
        if r <= 1e-6:
            continue
        d0, d1, d2 = d[0] / r, d[1] / r, d[2] / r
        t = 0.0
        t1 = t_end[i]
        while t < t1:
            te, tx, _, key = _march(o[0], o[1], o[2], d0, d1, d2, _inverse(d0), _inverse(d1), _inverse(d2), t, t1, occ,
                                    offs, dims, lo, vs, 0.0, 0, o[0], o[1], o[2], 0.0, field, ftop)
            if te < 0:
                break
            s = _slot(col_start, ukeys, key, dims[0, 2])
            if s >= 0:
                free[s] += 1
            t = tx + 1e-5


def anchored_lo(lo: float, anchor: float, top: float) -> float:
    """The highest grid start at or below ``lo`` from which ``anchor`` lies a whole number of
    top-level cells (``top`` metres) away, so that a face of every level passes through it."""
    start = anchor - np.ceil((anchor - lo) / top) * top
    return float(start if start <= lo else start - top)  # in case ceil's rounding lands above


class VoxelGrid:
    """Occupancy of the points that fall in ``box``, at ``voxel`` metres, with ``levels`` coarser levels."""

    def __init__(self, points: np.ndarray, voxel: float = 0.2, box: Box = ROI, levels: int = 4,
                 anchor_z: float | None = None) -> None:
        """``anchor_z``: a height where every level has a face (see ``anchored_lo``); the grid
        then starts up to one top-level cell below ``box`` instead of at its corner."""
        self.voxel = float(voxel)
        self.box = box
        self.lo = np.asarray(box.lo, dtype=np.float64).copy()
        if anchor_z is not None:
            self.lo[2] = anchored_lo(float(box.lo[2]), float(anchor_z), self.voxel * (1 << levels))
        extent = np.asarray(box.hi, dtype=np.float64) - self.lo
        step = 1 << levels
        n0 = (np.ceil(extent / voxel / step).astype(np.int64) * step).astype(np.int64)
        self.dims = np.stack([n0 >> lvl for lvl in range(levels + 1)]).astype(np.int64)
        sizes = self.dims.prod(axis=1)
        # one bit per cell, each level starting on a 64-bit word: the 0.2 m level of the ROI
        # is 24 M cells, 3 MB packed (it was 24 MB as bytes, and the casts waited on memory)
        words = (sizes + 63) // 64
        self.offs = (np.concatenate([[0], np.cumsum(words)[:-1]]) * 64).astype(np.int64)
        points = np.ascontiguousarray(points, dtype=np.float64)
        self.keys = _voxel_keys(points, self.lo, self.voxel, *[int(v) for v in n0])
        self.keys[~box.contains(points)] = -1  # the padding of the pyramid stays empty
        inside = self.keys >= 0
        self.ukeys, inverse, self.hits = np.unique(self.keys[inside], return_inverse=True, return_counts=True)
        self.point_slot = np.full(len(points), -1, np.int64)
        self.point_slot[inside] = inverse
        self.moments = _moments(points, self.point_slot, len(self.ukeys))
        self.means = self.moments[:, 1:4] / np.maximum(self.hits, 1)[:, None]
        self._make_planes()
        self.occ = np.zeros(int(words.sum()), np.uint64)
        _fill(self.occ, self.offs, self.dims, self.ukeys)
        self.col_start = _column_starts(self.ukeys, int(n0[0] * n0[1]), int(n0[2]))
        self._make_field()

    def _make_field(self) -> None:
        """The empty-box radii of the level-1 cells (``_slab_field``), rebuilt with the occupancy."""
        if len(self.dims) < 2:
            self.field = self.ftop = np.zeros(1, np.uint8)  # no level 1: no jumps
            return
        self.field = _slab_field(self.occ, int(self.offs[1]), *[int(v) for v in self.dims[1]])
        K = len(self.dims) - 1
        self.ftop = _slab_field(self.occ, int(self.offs[K]), *[int(v) for v in self.dims[K]])

    def _make_planes(self) -> None:
        """The surface of each occupied voxel (``_planes``, over the voxel and its cells up to
        level ``PLANE_LEVELS``), rebuilt with the occupancy."""
        ny0, nz0 = int(self.dims[0, 1]), int(self.dims[0, 2])
        k = self.ukeys
        a, b, c = k // (ny0 * nz0), (k // nz0) % ny0, k % nz0
        parents = np.zeros((PLANE_LEVELS, len(k)), np.int64)
        for lvl in range(1, PLANE_LEVELS + 1):
            key = ((a >> lvl) * (ny0 >> lvl) + (b >> lvl)) * (nz0 >> lvl) + (c >> lvl)
            if len(k):
                parents[lvl - 1] = np.unique(key, return_inverse=True)[1]
        self.planes = _planes(self.moments, parents)

    def kept(self, keep: np.ndarray) -> "VoxelGrid":
        """A grid of only the occupied voxels where ``keep`` (one flag per occupied voxel) is
        True, surfaces and empty-box radii rebuilt; this one is left as it is (it may be shared)."""
        out = copy.copy(self)
        out.ukeys = self.ukeys[keep]
        out.means = self.means[keep]
        out.hits = self.hits[keep]
        out.moments = self.moments[keep]
        out._make_planes()
        out.occ = np.zeros_like(self.occ)
        _fill(out.occ, out.offs, out.dims, out.ukeys)
        out.col_start = _column_starts(out.ukeys, int(out.dims[0, 0] * out.dims[0, 1]), int(out.dims[0, 2]))
        out._make_field()
        return out

    def freeze(self) -> "VoxelGrid":
        """Make every array of the grid read-only (a grid that several methods share); returns it."""
        for value in vars(self).values():
            if isinstance(value, np.ndarray):
                value.flags.writeable = False
        return self

    def free_counts(self, origins: np.ndarray, points: np.ndarray, t_end: np.ndarray) -> np.ndarray:
        free = np.zeros(len(self.ukeys), np.int64)
        _carve(
            np.ascontiguousarray(origins, dtype=np.float64), np.ascontiguousarray(points, dtype=np.float64),
            np.ascontiguousarray(t_end, dtype=np.float64), self.occ, self.offs, self.dims, self.lo, self.voxel,
            self.ukeys, self.col_start, free, self.field, self.ftop,
        )
        return free

    def cast(self, origin: np.ndarray, directions: np.ndarray, cone: float = 0.0, max_level: int = 0,
             cone_center: np.ndarray | None = None, surface: bool = False) -> np.ndarray:
        """Depth of the first hit per ray; NaN for rays that leave the grid without a hit.

        A cone's width at a point is ``cone`` times its distance from ``cone_center`` (the
        ray's origin by default; the past sensor to size it to the gaps of the past beams).
        ``surface``: the depth on the voxels' fitted surfaces (``_surface_depth``) instead of the
        projection of the hit voxel's mean (``_mean_depth``)."""
        origin = np.asarray(origin, dtype=np.float64)
        center = origin if cone_center is None else np.asarray(cone_center, dtype=np.float64)
        directions = np.ascontiguousarray(directions, dtype=np.float64)
        return _cast(
            origin, directions, np.asarray(self.box.lo, np.float64), np.asarray(self.box.hi, np.float64),
            self.occ, self.offs, self.dims, self.lo, self.voxel, float(cone),
            int(min(max_level, len(self.offs) - 1)), self.ukeys, self.col_start, self.means, center, self.field, self.ftop,
            self.planes, bool(surface),
        )
