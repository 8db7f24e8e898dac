"""The numba kernel of GMatch (`gscan.matching.gmatch` holds the specification, the parameters and the API).

`search(...)` runs the bounded hypothesis search of `gscan.matching.gmatch`'s module docstring on candidate pairs in
descriptor order. Member sets (A_s, A_b, survivors) are structure-of-arrays holding their coordinates, so
each filtering step is one branch-free (vectorised) pass computing g and the verdicts, then an
order-keeping compaction; the flip-over test runs on a Step's argmin only (a flipping argmin is set aside
for that Step). Compiled with `cache=True`, `nogil=True`.
"""
from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def _normal_z(P, a, b, c, view, collinear_sin):
    """(z, ok): z = unit normal of (P_a - P_b) x (P_a - P_c) dotted with view; ok False when near-collinear."""
    e1x = P[a, 0] - P[b, 0]
    e1y = P[a, 1] - P[b, 1]
    e1z = P[a, 2] - P[b, 2]
    e2x = P[a, 0] - P[c, 0]
    e2y = P[a, 1] - P[c, 1]
    e2z = P[a, 2] - P[c, 2]
    nx = e1y * e2z - e1z * e2y
    ny = e1z * e2x - e1x * e2z
    nz = e1x * e2y - e1y * e2x
    nn = np.sqrt(nx * nx + ny * ny + nz * nz)
    l1 = np.sqrt(e1x * e1x + e1y * e1y + e1z * e1z)
    l2 = np.sqrt(e2x * e2x + e2y * e2y + e2z * e2z)
    if nn <= collinear_sin * l1 * l2 or nn == 0.0:
        return 0.0, False
    return (nx * view[0] + ny * view[1] + nz * view[2]) / nn, True


@njit(cache=True, nogil=True)
def flips(ps, pt, i1, i2, i3, j1, j2, j3, view_s, view_t, flip_margin, collinear_sin):
    """True if triangle (i1, i2, i3) <-> (j1, j2, j3) is seen from opposite sides (flip-over)."""
    zs, oks = _normal_z(ps, i1, i2, i3, view_s, collinear_sin)
    if not oks:
        return False
    zt, okt = _normal_z(pt, j1, j2, j3, view_t, collinear_sin)
    if not okt:
        return False
    return zs * zt < 0.0 and abs(zs - zt) > flip_margin


# Member sets (A_s, A_b, survivors) are kept in structure-of-arrays form so that the filtering loops run
# without gathers or branches: F [7 x cap] float64 rows source xyz, target xyz, depth factor cf;
# I [3 x cap] int32 rows candidate index, source index, target index; G [cap] float64 running cost g.


@njit(cache=True, nogil=True)
def _member_set(cap):
    """(F [7 x cap] float64, I [3 x cap] int32, G [cap] float64), uninitialised."""
    return np.empty((7, cap)), np.empty((3, cap), np.int32), np.empty(cap)


@njit(cache=True, nogil=True, inline="always")
def _copy_member(F, I, k, Fo, Io, Go, w, g):
    """Member k of (F, I) to slot w of (Fo, Io, Go), with running cost g."""
    for r in range(7):
        Fo[r, w] = F[r, k]
    Io[0, w] = I[0, k]
    Io[1, w] = I[1, k]
    Io[2, w] = I[2, k]
    Go[w] = g


@njit(cache=True, nogil=True, error_model="numpy")
def keep_consistent(F, I, G, n, Fo, Io, Go, k_m, eps, eta, tg, tok):
    """Members k < n of (F, I, G) consistent with member k_m: delta(k_m, k) defined (one-to-one, within
    eta) and g = max(G[k], delta) <= eps. Written in order to (Fo, Io, Go) with g updated; these may be
    (F, I, G) themselves (in-place compaction). Returns (count, argmin of the new g (first on ties; -1 when
    none), its g). tg [>= n] float64, tok [>= n] bool: scratch. Two passes: a branch-free (vectorised)
    one computing g and the verdicts, then the compaction."""
    mx, my, mz, nx, ny, nz, cfm = F[0, k_m], F[1, k_m], F[2, k_m], F[3, k_m], F[4, k_m], F[5, k_m], F[6, k_m]
    mi = I[1, k_m]
    mj = I[2, k_m]
    xs, ys, zs, xt, yt, zt, cf, src, tgt = F[0], F[1], F[2], F[3], F[4], F[5], F[6], I[1], I[2]
    for k in range(n):
        dx = xs[k] - mx
        dy = ys[k] - my
        dz = zs[k] - mz
        ls = np.sqrt(dx * dx + dy * dy + dz * dz)
        dx = xt[k] - nx
        dy = yt[k] - ny
        dz = zt[k] - nz
        lt = np.sqrt(dx * dx + dy * dy + dz * dz)
        err = abs(ls - lt)
        g = max(G[k], err / ls)
        tg[k] = g
        tok[k] = (g <= eps) & (err < eta * max(cfm, cf[k])) & (ls > 0.0) & (src[k] != mi) & (tgt[k] != mj)
    w = 0
    arg = -1
    ga = 2.0
    for k in range(n):
        if tok[k]:
            g = tg[k]
            _copy_member(F, I, k, Fo, Io, Go, w, g)
            if g < ga:
                ga = g
                arg = w
            w += 1
    return w, arg, ga


@njit(cache=True, nogil=True, error_model="numpy")
def _keep_on_plane(F, I, G, n, a_s, a_t, n_s, n_t, cfa, eps, eta):
    """"triple" constraint, in place: keep members whose signed distances to the start planes agree
    (|h_s - h_t| < eta and |h_s - h_t| / |q_s - a_s| <= eps); g updated. a_* [3] plane points, n_* [3] unit normals."""
    w = 0
    for k in range(n):
        hs = n_s[0] * (F[0, k] - a_s[0]) + n_s[1] * (F[1, k] - a_s[1]) + n_s[2] * (F[2, k] - a_s[2])
        ht = n_t[0] * (F[3, k] - a_t[0]) + n_t[1] * (F[4, k] - a_t[1]) + n_t[2] * (F[5, k] - a_t[2])
        dx = F[0, k] - a_s[0]
        dy = F[1, k] - a_s[1]
        dz = F[2, k] - a_s[2]
        la = np.sqrt(dx * dx + dy * dy + dz * dz)
        err = abs(hs - ht)
        g = max(G[k], err / la)
        ok = (g <= eps) & (err < eta * max(cfa, F[6, k])) & (la > 0.0)
        _copy_member(F, I, k, F, I, G, w, g)
        w += ok
    return w


@njit(cache=True, nogil=True)
def _argmin(G, n):
    """(first index of the smallest G[:n] below 2, that value); (-1, 2.0) when none."""
    arg = -1
    ga = 2.0
    for k in range(n):
        if G[k] < ga:
            ga = G[k]
            arg = k
    return arg, ga


@njit(cache=True, nogil=True)
def _unit_normal(P, a, b, c):
    n = np.cross(P[b] - P[a], P[c] - P[a])
    return n / np.sqrt(np.sum(n * n))


@njit(cache=True, nogil=True, error_model="numpy")
def _dists_soa(X, Y, Z, a, out):
    x, y, z = X[a], Y[a], Z[a]
    for k in range(X.shape[0]):
        out[k] = np.sqrt((X[k] - x) ** 2 + (Y[k] - y) ** 2 + (Z[k] - z) ** 2)


@njit(cache=True, nogil=True, error_model="numpy")
def search(ps, pt, ci, cj, cf, fsrc, ft_max, view_s, view_t, T, L, K2, K3, eps_c, eta, mode, flip_margin,
            collinear_sin):
    """Returns (best [L] candidate indices, best_len, best_cost, hyp [H x 3], hyp_len, hyp_cost, hyp_pruned,
    hyp_list [H x L]: each hypothesis' list as grown (candidate indices, -1 past its length))."""
    C = ci.shape[0]
    Ns = ps.shape[0]
    n_seed = min(T, C)
    Hmax = n_seed * K2 * K3
    hyp = np.full((Hmax, 3), -1, np.int64)
    hyp_len = np.zeros(Hmax, np.int64)
    hyp_cost = np.ones(Hmax, np.float64)
    hyp_pruned = np.zeros(Hmax, np.bool_)
    hyp_list = np.full((Hmax, L), -1, np.int64)
    H = 0
    best = np.full(L, -1, np.int64)
    best_len = 0
    best_cost = 1.0
    cur = np.empty(L, np.int64)
    Xs = np.ascontiguousarray(ps[:, 0])
    Ys = np.ascontiguousarray(ps[:, 1])
    Zs = np.ascontiguousarray(ps[:, 2])
    Xt = np.ascontiguousarray(pt[:, 0])
    Yt = np.ascontiguousarray(pt[:, 1])
    Zt = np.ascontiguousarray(pt[:, 2])
    Ds = np.empty(Ns, np.float64)
    Dt = np.empty(pt.shape[0], np.float64)
    tolv = np.empty(Ns, np.float64)
    W = np.empty(C, np.int32)  # candidates passing the window test of the current seed
    # member sets A_s, A_b, survivors and scratch (tg, tok: keep_consistent; xk, xg: set-aside flip-overs),
    # grown to the largest A_s seen
    cap = 0
    FA, IA, GA = _member_set(0)
    FB, IB, GB = _member_set(0)
    FS, IS, GS = _member_set(0)
    xk = np.empty(0, np.int64)
    xg = np.empty(0)
    tg = np.empty(0)
    tok = np.empty(0, np.bool_)
    # effective tolerance: min(eps_c, best cost) once a full-length list exists; no list it cuts could win,
    # but the compacted member sets change which K2 / K3 members later levels try (see gmatch.py)
    eps_e = eps_c
    for s in range(n_seed):
        si = ci[s]
        sj = cj[s]
        _dists_soa(Xs, Ys, Zs, si, Ds)
        _dists_soa(Xt, Yt, Zt, sj, Dt)
        # A_s in two passes over the candidates: a branch-free window test against an upper bound of
        # the tolerance, min(eta * max(cf_s, fs_i, ft_max), eps_e * Ds[i]), then the exact test.
        cfs = cf[s]
        for k in range(Ns):
            tolv[k] = min(eta * max(cfs, fsrc[k], ft_max), eps_e * Ds[k])
        tolv[si] = -1.0  # one-to-one: nothing pairs with the seed's source keypoint
        Dt[sj] = -1e30  # ... nor with its target keypoint
        nw = 0
        for c in range(C):
            qi = ci[c]
            W[nw] = c
            nw += abs(Ds[qi] - Dt[cj[c]]) <= tolv[qi]
        if nw > cap:
            cap = max(nw, 2 * cap)
            FA, IA, GA = _member_set(cap)
            FB, IB, GB = _member_set(cap)
            FS, IS, GS = _member_set(cap)
            xk = np.empty(cap, np.int64)
            xg = np.empty(cap)
            tg = np.empty(cap)
            tok = np.empty(cap, np.bool_)
        na = 0
        for k in range(nw):
            c = W[k]
            qi = ci[c]
            qj = cj[c]
            ls = Ds[qi]
            err = abs(ls - Dt[qj])
            FA[0, na] = ps[qi, 0]
            FA[1, na] = ps[qi, 1]
            FA[2, na] = ps[qi, 2]
            FA[3, na] = pt[qj, 0]
            FA[4, na] = pt[qj, 1]
            FA[5, na] = pt[qj, 2]
            FA[6, na] = cf[c]
            IA[0, na] = c
            IA[1, na] = qi
            IA[2, na] = qj
            GA[na] = err / ls
            na += (err < eta * max(cfs, cf[c])) & (err / ls <= eps_e) & (ls > 0.0)
        # levels 2 and 3, grown as generated so that a full-length list tightens eps_e early:
        # b = the next member of A_s (at most K2 per seed); A_b = members of A_s consistent with b;
        # c = the first K3 members of A_b forming a valid triangle (s, b, c), each grown at once.
        nb_done = 0
        pos = 0  # next b position in A_s
        eps_a = eps_e  # tolerance A_s was filtered with
        while nb_done < K2 and pos < na:
            if eps_e < eps_a:  # a full-length list tightened the tolerance: compact A_s (order kept)
                w = 0
                newpos = na
                for k in range(na):
                    if k == pos:
                        newpos = w
                    if GA[k] <= eps_e:
                        _copy_member(FA, IA, k, FA, IA, GA, w, GA[k])
                        w += 1
                pos = min(newpos, w)
                na = w
                eps_a = eps_e
                if pos >= na:
                    break
            kb = pos
            pos += 1
            nb_done += 1
            b = IA[0, kb]
            bi = IA[1, kb]
            bj = IA[2, kb]
            gb = GA[kb]
            nab, _, _ = keep_consistent(FA, IA, GA, na, FB, IB, GB, kb, eps_e, eta, tg, tok)
            n3 = 0
            for kc in range(nab):
                if n3 >= K3:
                    break
                g0 = max(gb, GB[kc])
                if g0 > eps_e:
                    continue
                c = IB[0, kc]
                ic = IB[1, kc]
                jc = IB[2, kc]
                if not _normal_z(ps, si, bi, ic, view_s, collinear_sin)[1]:
                    continue  # degenerate triangle
                if not _normal_z(pt, sj, bj, jc, view_t, collinear_sin)[1]:
                    continue
                if mode == 1 and flips(ps, pt, si, bi, ic, sj, bj, jc, view_s, view_t, flip_margin,
                                        collinear_sin):
                    continue
                n3 += 1
                hyp[H, 0] = s
                hyp[H, 1] = b
                hyp[H, 2] = c
                hyp_cost[H] = g0
                hyp_len[H] = 3
                hyp_list[H, 0] = s
                hyp_list[H, 1] = b
                hyp_list[H, 2] = c
                if best_len == L and g0 >= best_cost:
                    hyp_pruned[H] = True
                    H += 1
                    continue
                # survivors: members of A_b consistent with c (and with the start plane in triple mode)
                nsv, arg, ga = keep_consistent(FB, IB, GB, nab, FS, IS, GS, kc, eps_e, eta, tg, tok)
                if mode == 2:
                    nsv = _keep_on_plane(FS, IS, GS, nsv, ps[si], pt[sj], _unit_normal(ps, si, bi, ic),
                                         _unit_normal(pt, sj, bj, jc), cfs, eps_e, eta)
                    arg, ga = _argmin(GS, nsv)
                cur[0] = s
                cur[1] = b
                cur[2] = c
                n = 3
                cost = g0
                pruned = False
                while n < L:
                    if n + nsv < best_len or (best_len == L and cost >= best_cost):
                        pruned = True
                        break
                    # the argmin of g (ties: descriptor order) among the survivors that do not flip over
                    # w.r.t. the last two matches: a flipping argmin is set aside for this Step only
                    if mode == 1 and arg >= 0:
                        i1 = ci[cur[n - 1]]
                        i2 = ci[cur[n - 2]]
                        j1 = cj[cur[n - 1]]
                        j2 = cj[cur[n - 2]]
                        nx_ = 0
                        while arg >= 0 and flips(ps, pt, i1, i2, IS[1, arg], j1, j2, IS[2, arg], view_s, view_t,
                                                  flip_margin, collinear_sin):
                            xk[nx_] = arg
                            xg[nx_] = GS[arg]
                            nx_ += 1
                            GS[arg] = 3.0
                            arg, ga = _argmin(GS, nsv)
                        for k in range(nx_):  # the flip-overs stay survivors
                            GS[xk[k]] = xg[k]
                    if arg < 0:
                        break
                    cur[n] = IS[0, arg]
                    n += 1
                    cost = max(cost, ga)
                    # the survivors consistent with the newest match, in place: O(#survivors) per Step
                    nsv, arg, ga = keep_consistent(FS, IS, GS, nsv, FS, IS, GS, arg, eps_e, eta, tg, tok)
                if n >= L and best_len == L and cost >= best_cost:
                    pruned = True
                hyp_len[H] = n
                hyp_cost[H] = cost
                hyp_pruned[H] = pruned
                hyp_list[H, :n] = cur[:n]
                H += 1
                if not pruned and (n > best_len or (n == best_len and cost < best_cost)):
                    best_len = n
                    best_cost = cost
                    best[:n] = cur[:n]
                    if best_len == L:
                        eps_e = min(eps_c, best_cost)
    return best, best_len, best_cost, hyp[:H], hyp_len[:H], hyp_cost[:H], hyp_pruned[:H], hyp_list[:H]


@njit(cache=True, nogil=True)
def second_smallest_per_row(d):
    """[Ns] float32 second-smallest value of each row of d [Ns x Nt] (Nt >= 2)."""
    out = np.empty(d.shape[0], np.float32)
    for i in range(d.shape[0]):
        a = np.inf
        b = np.inf
        for j in range(d.shape[1]):
            x = d[i, j]
            if x < b:
                if x < a:
                    b = a
                    a = x
                else:
                    b = x
        out[i] = b
    return out
