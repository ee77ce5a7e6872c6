"""Raw array algebra of preintegrated IMU deltas (internal).

An element is ``Delta(q, v, p, t, cov, jac)`` for the motion over an interval:
``q`` (…, 4) the rotation ΔR as a quaternion ``[qx, qy, qz, qw]``, ``v``/``p`` (…, 3)
Δv/Δp expressed in the frame at the start of the interval, ``t`` (…) its duration,
``cov`` (…, 9, 9) the covariance of the error ``[δφ, δv, δp]`` (Forster et al.'s chart:
``ΔR̃ = ΔR·Exp(δφ)``, ``Δṽ = Δv + δv``, ``Δp̃ = Δp + δp``) and ``jac`` (…, 9, 6) the
first-order derivatives of ``[φ, v, p]`` (same chart) w.r.t. the biases ``[b_g, b_a]``.

Composition (``a`` then ``b``) is associative::

    ΔR = ΔR_a·ΔR_b,   Δv = Δv_a + ΔR_a·Δv_b,   Δp = Δp_a + Δv_a·Δt_b + ΔR_a·Δp_b,
    Δt = Δt_a + Δt_b,  cov = F·cov_a·Fᵀ + G·cov_b·Gᵀ,  jac = F·jac_a + G·jac_b,

with F, G the exact Jacobians of the composed delta w.r.t. the errors of ``a`` and ``b``:

    F = [[ΔR_bᵀ, 0, 0], [−ΔR_a[Δv_b]×, I, 0], [−ΔR_a[Δp_b]×, Δt_b·I, I]],
    G = diag(I, ΔR_a, ΔR_a).

Composing a prefix with one sample gives exactly Forster et al.'s recurrences (their
A and B matrices), so a sequential scan and ``associative_scan`` agree to rounding;
:func:`window` computes the same end result in one parallel pass. ``cov``/``jac`` may be
``None`` (values only).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from ..lie import _quaternion as quat

Array = jax.Array


class Delta(NamedTuple):
    q: Array
    v: Array
    p: Array
    t: Array
    cov: Array | None
    jac: Array | None


class Noise(NamedTuple):
    """Continuous-time noise variances σ² of the samples: ``gyro`` and ``acc`` (3,)
    (discrete ones are σ²/dt) and ``integration`` () (GTSAM's integration covariance:
    ``σ_i²·dt`` added to the position block)."""

    gyro: Array
    acc: Array
    integration: Array


def _mm(a: Array, b: Array) -> Array:
    """Batched (…, 3, 3) @ (…, 3, k) as a fused multiply-sum (faster than tiny dots on CPU)."""
    return jnp.sum(a[..., :, :, None] * b[..., None, :, :], axis=-2)


def _cross_mat(v: Array, x: Array) -> Array:
    """[v]× X for X (…, 3, k), column-wise cross products."""
    v = v[..., :, None]
    return jnp.stack(
        [
            v[..., 1, :] * x[..., 2, :] - v[..., 2, :] * x[..., 1, :],
            v[..., 2, :] * x[..., 0, :] - v[..., 0, :] * x[..., 2, :],
            v[..., 0, :] * x[..., 1, :] - v[..., 1, :] * x[..., 0, :],
        ],
        -2,
    )


def _apply_f(ra: Array, rb_t: Array, vb: Array, pb: Array, tb: Array, x: Array) -> Array:
    """F·X for X (…, 9, k)."""
    xf, xv, xp = x[..., 0:3, :], x[..., 3:6, :], x[..., 6:9, :]
    new_f = _mm(rb_t, xf)
    new_v = xv - _mm(ra, _cross_mat(vb, xf))
    new_p = xp + tb[..., None, None] * xv - _mm(ra, _cross_mat(pb, xf))
    return jnp.concatenate([new_f, new_v, new_p], -2)


def _apply_g(ra: Array, y: Array) -> Array:
    """G·Y for Y (…, 9, k)."""
    return jnp.concatenate([y[..., 0:3, :], _mm(ra, y[..., 3:6, :]), _mm(ra, y[..., 6:9, :])], -2)


def _sandwich(apply: object, s: Array) -> Array:
    """M·S·Mᵀ for symmetric S, as M·(M·S)ᵀ."""
    ms = apply(s)  # type: ignore[operator]
    return apply(jnp.swapaxes(ms, -1, -2))  # type: ignore[operator]


def compose(a: Delta, b: Delta) -> Delta:
    """The delta of interval ``a`` followed by interval ``b`` (broadcasts)."""
    ra = quat.to_matrix(a.q)
    q = quat.multiply(a.q, b.q)
    v = a.v + quat.rotate(a.q, b.v)
    p = a.p + a.v * b.t[..., None] + quat.rotate(a.q, b.p)
    t = a.t + b.t
    cov = jac = None
    if a.cov is not None or a.jac is not None:
        rb_t = jnp.swapaxes(quat.to_matrix(b.q), -1, -2)
        f = lambda x: _apply_f(ra, rb_t, b.v, b.p, b.t, x)  # noqa: E731
        g = lambda y: _apply_g(ra, y)  # noqa: E731
        if a.cov is not None:
            cov = _sandwich(f, a.cov) + _sandwich(g, b.cov)
        if a.jac is not None:
            jac = f(a.jac) + g(b.jac)
    return Delta(q, v, p, t, cov, jac)


def samples(omega: Array, acc: Array, dt: Array, noise: Noise | None, with_jac: bool) -> Delta:
    """One element per bias-corrected sample (…, 3): ``ΔR = Exp(ω dt)``, ``Δv = a dt``,
    ``Δp = ½ a dt²``; noise covariance (``noise``: :class:`Noise`, ``None`` for none) and
    bias Jacobians of a zero-order-hold sample."""
    phi = omega * dt[..., None]
    q = quat.exp(phi)
    v = acc * dt[..., None]
    p = 0.5 * v * dt[..., None]
    cov = jac = None
    if noise is not None or with_jac:
        jr = quat.jl(-phi)  # right Jacobian of Exp at ω dt
    if noise is not None:
        eye = jnp.eye(3, dtype=omega.dtype)
        d = dt[..., None, None]
        s_ff = jnp.einsum("...ij,j,...kj->...ik", jr, noise.gyro, jr) * d
        s_a = jnp.broadcast_to(eye * noise.acc, (*dt.shape, 3, 3))
        s_pp = s_a * d**3 / 4.0 + eye * (noise.integration * d)
        z = jnp.zeros_like(s_ff)
        cov = jnp.concatenate(
            [
                jnp.concatenate([s_ff, z, z], -1),
                jnp.concatenate([z, s_a * d, s_a * d**2 / 2.0], -1),
                jnp.concatenate([z, s_a * d**2 / 2.0, s_pp], -1),
            ],
            -2,
        )
    if with_jac:
        d = dt[..., None, None]
        eye = jnp.broadcast_to(jnp.eye(3, dtype=omega.dtype), jr.shape)
        z = jnp.zeros_like(jr)
        jac = jnp.concatenate(
            [
                jnp.concatenate([-jr * d, z], -1),
                jnp.concatenate([z, -eye * d], -1),
                jnp.concatenate([z, -eye * d**2 / 2.0], -1),
            ],
            -2,
        )
    return Delta(q, v, p, dt, cov, jac)


def cumulative(op: Callable[[Any, Any], Any], elems: Any, identity: Any) -> Any:
    """Inclusive prefix products ``e_0, e_0·e_1, …`` along axis 0 of an associative ``op``
    (broadcasting over leading axes) with neutral element ``identity`` (no axis 0).

    On CPU a two-level scan (blocks of ~√N scanned side by side, then the block totals):
    O(N) work, ~2√N sequential steps, and much cheaper to compile than
    ``lax.associative_scan`` (log-depth, used on accelerators)."""
    if jax.default_backend() != "cpu":
        return jax.lax.associative_scan(op, elems, axis=0)
    n = jax.tree.leaves(elems)[0].shape[0]
    blk = max(1, math.isqrt(n - 1) + 1) if n > 1 else 1
    nb = -(-n // blk)
    pad = nb * blk - n

    def blocks(x: Array, e: Array) -> Array:
        e = jnp.broadcast_to(e.astype(x.dtype), (pad, *x.shape[1:]))
        return jnp.swapaxes(jnp.concatenate([x, e], 0).reshape(nb, blk, *x.shape[1:]), 0, 1)

    def step(c: Any, x: Any) -> tuple[Any, Any]:
        c = op(c, x)
        return c, c

    xs = jax.tree.map(blocks, elems, identity)  # (blk, nb, …)
    init = jax.tree.map(lambda e, x: jnp.broadcast_to(e, x.shape[1:]), identity, xs)
    _, inner = jax.lax.scan(step, init, xs)  # prefixes within each block
    _, outer = jax.lax.scan(step, identity, jax.tree.map(lambda x: x[-1], inner))
    before = jax.tree.map(lambda e, o: jnp.concatenate([e[None], o[:-1]], 0), identity, outer)
    out = op(jax.tree.map(lambda b: b[None], before), inner)  # (blk, nb, …)
    return jax.tree.map(lambda x: jnp.swapaxes(x, 0, 1).reshape(nb * blk, *x.shape[2:])[:n], out)


def _quat_identity(dtype: Any) -> Array:
    return jnp.array([0.0, 0.0, 0.0, 1.0], dtype)


def prefix_values(
    omega: Array, acc: Array, dt: Array
) -> tuple[Array, Array, Array, Array, Array, Array]:
    """Cumulative values after every sample (N, …) of bias-corrected samples (N, 3):
    ``(q_incl, v_incl, p_incl, t_incl, q_excl, u)`` with ``q_excl`` the rotation before
    each sample and ``u = ΔR_{<k} a_k dt_k`` its velocity increment. Rotations by an
    associative scan of quaternion products, velocities and positions by cumulative
    sums."""
    d = dt[..., None]
    ident = _quat_identity(omega.dtype)
    q_incl = cumulative(quat.multiply, quat.exp(omega * d), ident)
    q_excl = jnp.concatenate([jnp.broadcast_to(ident, q_incl[:1].shape), q_incl[:-1]], 0)
    u = quat.rotate(q_excl, acc * d)
    v_incl = jnp.cumsum(u, 0)
    p_incl = jnp.cumsum((v_incl - u) * d + 0.5 * u * d, 0)
    return q_incl, v_incl, p_incl, jnp.cumsum(dt, 0), q_excl, u


def _rows(x: Array) -> list[Array]:
    """(N, k) → k arrays (N,)."""
    return [x[:, i] for i in range(x.shape[-1])]


def _quat_rot(q: list[Array]) -> list[list[Array]]:
    """Rotation matrix entries R[i][j] (each (N,)) of quaternion parts [x, y, z, w]."""
    x, y, z, w = q
    xx, yy, zz, xy, xz, yz = x * x, y * y, z * z, x * y, x * z, y * z
    wx, wy, wz = w * x, w * y, w * z
    return [
        [1 - 2 * (yy + zz), 2 * (xy - wz), 2 * (xz + wy)],
        [2 * (xy + wz), 1 - 2 * (xx + zz), 2 * (yz - wx)],
        [2 * (xz - wy), 2 * (yz + wx), 1 - 2 * (xx + yy)],
    ]


def _jl_parts(phi: list[Array]) -> list[list[Array]]:
    """Left Jacobian entries (1 − bθ²)I + a[φ]× + bφφᵀ of rotation vectors (N,) × 3."""
    x, y, z = phi
    t = x * x + y * y + z * z
    a, b, _, _ = quat.jl_coeffs(t)
    d = 1 - b * t
    bx, by, bz = b * x, b * y, b * z
    ax, ay, az = a * x, a * y, a * z
    return [
        [d + bx * x, bx * y - az, bx * z + ay],
        [by * x + az, d + by * y, by * z - ax],
        [bz * x - ay, bz * y + ax, d + bz * z],
    ]


def _matmul_parts(a: list[list[Array]], b: list[list[Array]]) -> list[list[Array]]:
    return [[a[i][0] * b[0][j] + a[i][1] * b[1][j] + a[i][2] * b[2][j] for j in range(3)]
            for i in range(3)]


def _neg_cross_cols(s: list[Array], m: list[list[Array]]) -> list[list[Array]]:
    """Entries of −[s]× M (column-wise −s × M[:, j])."""
    return [
        [s[2] * m[1][j] - s[1] * m[2][j] for j in range(3)],
        [s[0] * m[2][j] - s[2] * m[0][j] for j in range(3)],
        [s[1] * m[0][j] - s[0] * m[1][j] for j in range(3)],
    ]


def _chart_map(rn_t: Array, x: Array) -> Array:
    """blockdiag(ΔRᵀ, I, I)·X for X (9, k): start-frame rotation errors → Forster's."""
    return jnp.concatenate([rn_t @ x[0:3], x[3:9]], 0)


def window(omega: Array, acc: Array, dt: Array, noise: Noise | None, with_jac: bool) -> Delta:
    """The delta of a whole window of bias-corrected samples (N, 3), all at once.

    Instead of propagating the covariance sample by sample, each sample's noise is mapped
    straight to the window's end error by its closed-form gain H_k (9×6; the product of
    the composition Jacobians G of everything before it and F of everything after it,
    which only needs prefix/suffix values). In the start-frame chart (ΔR̃ = Exp(δθ)·ΔR,
    additive δv, δp), a gyro rate error e at sample k moves the end state by
    ``[M_k e, −[S_k]× M_k e, −[P_k]× M_k e]·dt_k`` with ``M_k = ΔR_{<k} Jl(ω_k dt_k)``,
    ``S_k = Δv − Δv_{≤k}``, ``P_k = Δp − Δp_{≤k} − Δv_{≤k}·t_k`` (t_k: time after sample
    k); an accelerometer error e by ``[0, R_k e, (dt_k/2 + t_k) R_k e]·dt_k`` with
    ``R_k = ΔR_{<k}``. Hence the bias Jacobian ``−Σ_k H_k dt_k`` and the covariance
    ``Σ_k H_k diag(σ_g², σ_a²) H_kᵀ dt_k`` (one matrix product over all samples),
    rotated at the end to Forster's chart (δφ = ΔRᵀ δθ). Same results as the sequential
    recurrences, with no sequential dependency besides the prefix values.

    Layout: every per-sample quantity is a list of (N,) arrays (sample axis last and
    contiguous), so XLA vectorises the arithmetic over samples (and over vmapped windows)
    instead of looping over 3×3 blocks; the gains are stacked once as (9, 3N) for the
    covariance product."""
    q_incl, v_incl, p_incl, t_incl, q_excl, _ = prefix_values(omega, acc, dt)
    qn, vn, pn, tn = q_incl[-1], v_incl[-1], p_incl[-1], t_incl[-1]
    if noise is None and not with_jac:
        return Delta(qn, vn, pn, tn, None, None)
    dtype = omega.dtype
    n = dt.shape[0]
    ts = tn - t_incl  # time after each sample (N,)
    s = vn - v_incl  # S_k
    pk = pn - p_incl - v_incl * ts[:, None]  # P_k
    r_ex = _quat_rot(_rows(q_excl))  # ΔR_{<k}
    m = _matmul_parts(r_ex, _jl_parts(_rows(omega * dt[:, None])))
    # materialise the shared per-sample factors once: XLA:CPU would otherwise duplicate
    # their (cheap, elementwise) producers into each consumer
    r_flat, m_flat, s, pk = jax.lax.optimization_barrier(
        (jnp.stack(sum(r_ex, [])), jnp.stack(sum(m, [])), s, pk)
    )
    r_ex = [[r_flat[3 * i + j] for j in range(3)] for i in range(3)]
    m = [[m_flat[3 * i + j] for j in range(3)] for i in range(3)]
    sm, pm = _neg_cross_cols(_rows(s), m), _neg_cross_cols(_rows(pk), m)
    # gyro gains per unit time: rows [φ, v, p] (9) × (column j, sample k) as (9, 3N)
    zg = jnp.concatenate([m_flat, jnp.stack(sum(sm, [])), jnp.stack(sum(pm, []))])
    zg = zg.reshape(9, 3 * n)
    gain_p = 0.5 * dt + ts  # accelerometer gain of the position rows
    rn_t = quat.to_matrix(qn).T
    cov = jac = None
    if noise is not None:
        wg, wa = noise.gyro, noise.acc
        cg = zg @ (zg * (wg[:, None] * dt).reshape(-1)).T
        # accelerometer: Σ_k R_k diag(σ_a²) R_kᵀ·c_k for c = dt, gain_p·dt, gain_p²·dt
        e = jnp.stack([
            sum(wa[c] * r_ex[i][c] * r_ex[j][c] for c in range(3))
            for i, j in ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))
        ])
        sums = e @ jnp.stack([dt, gain_p * dt, gain_p * gain_p * dt], -1)  # (6, 3)
        sym = jnp.asarray([[0, 1, 2], [1, 3, 4], [2, 4, 5]])
        vv, vp, pp = (sums[:, c][sym] for c in range(3))
        ca = jnp.block([[vv, vp], [vp, pp]])
        cov = cg + jnp.pad(ca, ((3, 0), (3, 0)))
        cov = _chart_map(rn_t, _chart_map(rn_t, cov).T)
        cov = cov.at[6:9, 6:9].add(jnp.eye(3, dtype=dtype) * (noise.integration * tn))
    if with_jac:
        jg = -(zg.reshape(27, n) @ dt).reshape(9, 3)
        ja = -(r_flat @ jnp.stack([dt, gain_p * dt], -1))  # (9, 2): rows (i, j)
        ja = jnp.concatenate([ja[:, 0].reshape(3, 3), ja[:, 1].reshape(3, 3)])
        jac = jnp.concatenate([jg, jnp.pad(ja, ((3, 0), (0, 0)))], -1)
        jac = _chart_map(rn_t, jac)
    return Delta(qn, vn, pn, tn, cov, jac)


def prefix(elems: Delta) -> Delta:
    """All prefix products along axis 0 (associative scan of :func:`compose`)."""
    d = elems.q.dtype
    ident = Delta(
        _quat_identity(d), jnp.zeros(3, d), jnp.zeros(3, d), jnp.zeros((), d),
        None if elems.cov is None else jnp.zeros((9, 9), d),
        None if elems.jac is None else jnp.zeros((9, 6), d),
    )
    return cumulative(compose, elems, ident)


