"""The numba kernel of `gscan.geometry.plane.ransac_plane`'s scoring: the signed heights of every point above
every hypothesis plane, counted as inliers (|h| < d) and as points behind the plane (h < -d) in one pass,
without the [N x m] height matrix.

A height is n . p + offset with the dot product as fused multiply-adds in coordinate order,
fma(p_z, n_z, fma(p_y, n_y, p_x n_x)) + offset: deterministic whatever the BLAS, and the value x86-64
OpenBLAS's matrix product `S @ normals.T + offset` gives. On a CPU without fused multiply-add instructions
(HAS_FMA False) the RANSAC scores with that matrix product: emulated, the kernel would be slower than it.
Compiled with `cache=True`, `nogil=True`; imported on first use, so that importing `gscan.geometry` does not
load numba.
"""
from __future__ import annotations

import platform

import numpy as np
from llvmlite import binding, ir
from numba import njit
from numba.core import cgutils, types
from numba.extending import intrinsic

HAS_FMA = platform.machine().lower() in ("aarch64", "arm64") or \
    "+fma" in binding.get_host_cpu_features().flatten().split(",")


@intrinsic
def _fma(typingctx, a, b, c):
    """a * b + c rounded once (LLVM's llvm.fma.f64)."""
    sig = types.float64(types.float64, types.float64, types.float64)

    def codegen(context, builder, signature, args):
        fnty = ir.FunctionType(ir.DoubleType(), [ir.DoubleType()] * 3)
        return builder.call(cgutils.get_or_insert_function(builder.module, fnty, "llvm.fma.f64"), args)

    return sig, codegen


@njit(cache=True, nogil=True, inline="always")
def _height(S, i, normals, offsets, j):
    return _fma(S[i, 2], normals[j, 2], _fma(S[i, 1], normals[j, 1], S[i, 0] * normals[j, 0])) + offsets[j]


@njit(cache=True, nogil=True)
def plane_counts(S, normals, offsets, d):
    """(inliers [m], behind [m]) int64 of planes normals [m x 3], offsets [m] over points S [N x 3] with
    tolerances d [N]."""
    m = normals.shape[0]
    inl = np.zeros(m, np.int64)
    behind = np.zeros(m, np.int64)
    for i in range(S.shape[0]):
        di = d[i]
        for j in range(m):
            h = _height(S, i, normals, offsets, j)
            inl[j] += abs(h) < di
            behind[j] += h < -di
    return inl, behind


@njit(cache=True, nogil=True)
def plane_inliers(S, normals, offsets, j, d):
    """[N] bool: the inliers of plane j (as `plane_counts` counts them)."""
    out = np.empty(S.shape[0], np.bool_)
    for i in range(S.shape[0]):
        out[i] = abs(_height(S, i, normals, offsets, j)) < d[i]
    return out
