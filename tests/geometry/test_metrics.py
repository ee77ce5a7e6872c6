"""APE / RPE against hand-computed values on small trajectories; association; alignment;
PyPose parity (peer)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxpose.geometry import ape, associate, error_stats, rpe
from jaxpose.lie import SE3, Sim3

from .conftest import pypose


def _poses(t: np.ndarray, yaw: np.ndarray | None = None) -> SE3:
    """SE3 trajectory from translations (N, 3) and yaw angles (N,)."""
    yaw = np.zeros(len(t)) if yaw is None else yaw
    q = np.stack([np.zeros_like(yaw), np.zeros_like(yaw), np.sin(yaw / 2), np.cos(yaw / 2)], -1)
    return SE3(jnp.asarray(np.concatenate([t, q], -1)))


def test_error_stats_hand_values():
    e = np.array([3.0, 1.0, 4.0, 1.0, 5.0, 9.0])
    s = error_stats(e)
    assert float(s.max) == 9 and float(s.min) == 1
    assert float(s.mean) == pytest.approx(23 / 6)
    assert float(s.median) == pytest.approx(3.5)  # mean of 3 and 4
    assert float(s.sse) == pytest.approx(133)
    assert float(s.rmse) == pytest.approx(np.sqrt(133 / 6))
    assert float(s.std) == pytest.approx(np.sqrt(133 / 6 - (23 / 6) ** 2))
    masked = error_stats(e, valid=[True, True, True, False, False, False])
    assert float(masked.median) == 3 and float(masked.mean) == pytest.approx(8 / 3)
    assert np.isnan(float(error_stats(e, valid=np.zeros(6, bool)).mean))


@pytest.mark.parametrize("errors", [[1.0, 2.0, np.nan], [1.0, np.inf, np.inf],
                                    [1.0, 2.0, np.inf, np.inf], [np.nan, 0.0, 0.0]])
def test_error_stats_propagate_nan_and_inf_as_numpy(errors):
    """A NaN error gave RMSE 0, std 0 and the median of the others; an inf median gave 0:
    a broken trajectory (NaN pose) looked perfect in ape()/rpe()."""
    e = np.asarray(errors)
    got = error_stats(e)
    with np.errstate(invalid="ignore"):
        want = dict(max=e.max(), min=e.min(), mean=e.mean(), median=np.median(e),
                    rmse=np.sqrt(np.mean(e * e)), sse=np.sum(e * e), std=e.std())
    for name, value in want.items():
        np.testing.assert_array_equal(float(getattr(got, name)), value, err_msg=name)
    # a masked-out NaN plays no part
    np.testing.assert_array_equal(float(error_stats(e, valid=np.isfinite(e)).median),
                                  np.median(e[np.isfinite(e)]))
    with pytest.raises(ValueError, match=r"error_stats\(errors\): expected at least one"):
        error_stats(np.zeros((2, 0)))


def test_ape_of_a_nan_pose_is_not_a_perfect_score():
    ref = _poses(np.array([[0.0, 0, 0], [1, 0, 0], [2, 0, 0]]))
    est = np.asarray(ref.data).copy()
    est[1, 0] = np.nan
    assert np.isnan(float(ape(ref, SE3(jnp.asarray(est))).stats.rmse))


def test_ape_hand_values():
    ref = _poses(np.array([[0.0, 0, 0], [1, 0, 0], [2, 0, 0], [3, 0, 0]]))
    # estimate: translations off by 0, 1, 2, 2 along y; last also yawed by 0.3 rad
    est = _poses(np.array([[0.0, 0, 0], [1, 1, 0], [2, 2, 0], [3, 2, 0]]),
                 np.array([0, 0, 0, 0.3]))
    out = ape(ref, est)
    np.testing.assert_allclose(out.errors, [0, 1, 2, 2], atol=1e-15)
    assert float(out.stats.rmse) == pytest.approx(np.sqrt(9 / 4))
    assert float(out.stats.median) == pytest.approx(1.5)
    rad = ape(ref, est, etype="radian")
    np.testing.assert_allclose(rad.errors, [0, 0, 0, 0.3], atol=1e-12)
    np.testing.assert_allclose(ape(ref, est, etype="degree").errors[3], np.rad2deg(0.3))
    # ‖R − I‖_F = 2√2 sin(θ/2) for a rotation by θ
    rot = ape(ref, est, etype="rotation")
    np.testing.assert_allclose(rot.errors[3], 2 * np.sqrt(2) * np.sin(0.15), rtol=1e-12)
    # pose: T_e⁻¹ T_r = (Rᵀ, −Rᵀ(t_e − t_r)); ‖· − I‖_F² = ‖R − I‖² + ‖t_e − t_r‖²
    pose = ape(ref, est, etype="pose")
    np.testing.assert_allclose(pose.errors[3], np.sqrt(8 * np.sin(0.15) ** 2 + 4), rtol=1e-12)


def test_alignment_recovers_similarity(rng):
    ref = SE3.exp(jnp.asarray(np.cumsum(rng.normal(size=(12, 6)) * 0.3, 0)))
    q = np.array([0.1, 0.2, -0.3, 0.9])
    s = Sim3(jnp.asarray(np.r_[0.5, -1.0, 2.0, q / np.linalg.norm(q), 0.5]))
    # est = s⁻¹ ∘ ref (rotations composed, translations mapped)
    inv = s.inv()
    est = SE3(jnp.concatenate([inv.act(ref.translation()),
                               inv.rotation().compose(ref.rotation()).data], -1))
    out = ape(ref, est, align="sim3", etype="pose")
    np.testing.assert_allclose(out.errors, 0.0, atol=1e-12)
    np.testing.assert_allclose(out.alignment.matrix(), s.matrix(), atol=1e-12)
    se3 = ape(ref, est, align="se3")
    assert float(se3.stats.rmse) > 0.1  # a rigid alignment cannot undo the scale
    origin = ape(ref, ref @ SE3.exp(jnp.array([1.0, 0, 0, 0, 0, 0.2])), align="origin")
    assert float(origin.errors[0]) == pytest.approx(0.0, abs=1e-14)


def test_association_and_rpe_hand_values():
    ref_t = np.array([0.0, 1.0, 2.0, 3.0, 4.0, 5.0])
    est_t = np.array([0.004, 1.2, 2.003, 2.999, 4.001])  # 1.2 does not match
    ri, ei, ok = associate(ref_t, est_t, max_diff=0.01)
    np.testing.assert_array_equal(ri, [0, 1, 2, 3, 4])
    np.testing.assert_array_equal(ei, [0, 1, 2, 3, 4])
    np.testing.assert_array_equal(ok, [True, False, True, True, True])
    ri, ei, ok = associate(ref_t, est_t + 0.5, max_diff=0.01, offset=-0.5)
    np.testing.assert_array_equal(ok, [True, False, True, True, True])
    # RPE: reference moves 1 m per frame along x; estimate 1.1 m per frame
    ref = _poses(np.c_[np.arange(6.0), np.zeros((6, 2))])
    est = _poses(np.c_[np.arange(5.0) * 1.1, np.zeros((5, 2))])
    out = rpe(ref, est, ref_t, est_t, delta=1, all_pairs=True)
    # associated frames 0, 2, 3, 4 (compacted); pairs (0,2), (2,3), (3,4) in reference time
    np.testing.assert_array_equal(out.valid, [True, True, True, False, False])
    np.testing.assert_allclose(np.asarray(out.errors)[:3], [0.2, 0.1, 0.1], atol=1e-12)
    stride = rpe(ref, est, ref_t, est_t, delta=2)  # frames 0, 2 of the compacted list
    assert int(np.sum(stride.valid)) == 1
    np.testing.assert_allclose(stride.errors[0], 0.3, atol=1e-12)


def test_jit_vmap_grad(rng):
    ref = SE3.exp(jnp.asarray(np.cumsum(rng.normal(size=(2, 8, 6)) * 0.3, 1)))
    noise = jnp.asarray(rng.normal(size=(2, 8, 6)) * 0.05)

    def f(r, n):
        return rpe(SE3(r), SE3(r) @ SE3.exp(n), etype="radian", align="se3").stats.rmse

    vm = jax.jit(jax.vmap(jax.value_and_grad(f, argnums=1)))(ref.data, noise)
    np.testing.assert_allclose(vm[0], [f(ref.data[i], noise[i]) for i in range(2)], rtol=1e-12)
    assert np.all(np.isfinite(vm[1]))


@pytest.mark.peer
@pytest.mark.slow
def test_pypose_parity(rng):
    pp = pypose()
    import warnings

    import torch

    ref = SE3.exp(jnp.asarray(np.cumsum(rng.normal(size=(20, 6)) * 0.2, 0)))
    est = SE3.exp(ref.log().data + jnp.asarray(rng.normal(size=(20, 6)) * 0.05))
    rs = np.arange(20.0) * 0.1
    es = rs[3:] + 0.003
    tr = lambda x: torch.tensor(np.asarray(x))
    for etype in ("translation", "pose", "degree"):
        for align, kw in [(None, {}), ("sim3", {"align": True, "scale": True})]:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                want = pp.metric.rpe(tr(rs), pp.SE3(tr(ref.data)), tr(es),
                                     pp.SE3(tr(est.data[3:])), etype=etype, delta=2, **kw)
                want_a = pp.metric.ape(tr(rs), pp.SE3(tr(ref.data)), tr(es),
                                       pp.SE3(tr(est.data[3:])), etype=etype, **kw)
            got = rpe(ref, est[3:], rs, es, etype=etype, align=align, delta=2).stats
            got_a = ape(ref, est[3:], rs, es, etype=etype, align=align).stats
            for key in ("Max", "Min", "Mean", "RMSE", "SSE"):
                assert float(getattr(got, key.lower())) == pytest.approx(float(want[key]),
                                                                         rel=1e-9, abs=1e-12)
                assert float(getattr(got_a, key.lower())) == pytest.approx(
                    float(want_a[key]), rel=1e-9, abs=1e-12)


def test_bad_input():
    p = SE3.identity((4,))
    with pytest.raises(ValueError, match=r"ape\(ref, est\).*equal lengths"):
        ape(p, SE3.identity((5,)))
    with pytest.raises(ValueError, match=r"ape\(etype\)"):
        ape(p, p, etype="angle")
    with pytest.raises(ValueError, match=r"rpe\(align\)"):
        rpe(p, p, align="affine")
    with pytest.raises(ValueError, match=r"rpe\(delta\)"):
        rpe(p, p, delta=0)
    with pytest.raises(ValueError, match=r"give both or neither"):
        ape(p, p, np.arange(4.0))
    with pytest.raises(TypeError, match=r"ape\(est\).*SE3"):
        ape(p, np.zeros((4, 7)))
    with pytest.raises(ValueError, match=r"associate\(ref_stamps, est_stamps\)"):
        associate(np.zeros(0), np.zeros(3))


def _pairs_by_distance(t: np.ndarray, delta: float, tol: float, all_pairs: bool):
    """evo/PyPose path-distance pairing, written out in plain Python."""
    steps = np.linalg.norm(np.diff(t, axis=0), axis=1)
    if all_pairs:
        d = np.concatenate([[0.0], np.cumsum(steps)])
        pairs = []
        for i in range(len(d) - 1):
            rest = np.abs(d[i + 1:] - d[i] - delta)
            j = int(np.argmin(rest))
            if rest[j] <= tol:
                pairs.append((i, i + 1 + j))
        return pairs
    chosen, path = [], 0.0
    for i, s in enumerate(np.concatenate([[0.0], steps])):
        path += s
        if path >= delta:
            chosen.append(i)
            path = 0.0
    return list(zip(chosen[:-1], chosen[1:], strict=True))


@pytest.mark.parametrize("all_pairs", [False, True])
def test_rpe_by_distance_matches_plain_python_pairing(rng, all_pairs):
    n = 60
    t = np.cumsum(rng.uniform(0.05, 0.4, size=(n, 3)), 0)
    t[10:14] = t[10]  # standing still: ties in the path distance
    yaw = rng.uniform(-1, 1, n)
    ref = _poses(t, yaw)
    est_t = t + rng.normal(scale=0.05, size=t.shape)
    est = _poses(est_t, yaw + rng.normal(scale=0.01, size=n))
    out = rpe(ref, est, pair_by="distance", delta=1.5, all_pairs=all_pairs, etype="translation")
    pairs = _pairs_by_distance(est_t, 1.5, 0.15, all_pairs)
    got = [tuple(p) for p, ok in zip(np.asarray(out.pairs), np.asarray(out.valid)) if ok]
    assert got == pairs and len(pairs) > 5
    r, e = np.asarray(ref.data), np.asarray(est.data)

    def rel(x: np.ndarray, i: int, j: int) -> np.ndarray:  # 4x4 of x_i^-1 x_j (numpy)
        m = [np.asarray(SE3(x[k]).matrix()) for k in (i, j)]
        return np.linalg.inv(m[0]) @ m[1]

    expect = [np.linalg.norm((np.linalg.inv(rel(r, i, j)) @ rel(e, i, j))[:3, 3])
              for i, j in pairs]
    assert float(out.stats.mean) == pytest.approx(np.mean(expect), rel=1e-12)
    # pairs on the reference path instead
    by_ref = rpe(ref, est, pair_by="distance", delta=1.5, all_pairs=all_pairs,
                 pairs_from="ref")
    got = [tuple(p) for p, ok in zip(np.asarray(by_ref.pairs), np.asarray(by_ref.valid)) if ok]
    assert got == _pairs_by_distance(t, 1.5, 0.15, all_pairs)


def test_rpe_by_distance_bad_input():
    ref = _poses(np.arange(12.0)[:, None] * np.ones(3))
    with pytest.raises(ValueError, match=r"rpe\(pair_by\)"):
        rpe(ref, ref, pair_by="time")
    with pytest.raises(ValueError, match=r"rpe\(delta\)"):
        rpe(ref, ref, pair_by="distance", delta=0.0)
    with pytest.raises(TypeError, match=r"rpe\(delta\) \(a frame count\): expected an int"):
        rpe(ref, ref, delta=1.5)  # frame pairing needs an int
    with pytest.raises(ValueError, match=r"rpe\(pairs_from\)"):
        rpe(ref, ref, pair_by="distance", pairs_from="gt")
    # a path shorter than delta: no valid pair, NaN statistics (nothing to average)
    out = rpe(ref, ref, pair_by="distance", delta=1e3)
    assert not bool(out.valid.any()) and np.isnan(float(out.stats.mean))


@pytest.mark.peer
def test_rpe_by_distance_matches_pypose(rng):
    pp = pypose()
    import torch

    n = 40
    t = np.cumsum(rng.uniform(0.05, 0.4, size=(n, 3)), 0)
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    ref = np.concatenate([t, q], 1)
    est = ref.copy()
    est[:, :3] += rng.normal(scale=0.05, size=(n, 3))
    stamps = np.arange(n, dtype=float)
    for all_pairs in (False, True):
        theirs = pp.metric.rpe(torch.tensor(stamps), pp.SE3(torch.tensor(ref)),
                               torch.tensor(stamps), pp.SE3(torch.tensor(est)),
                               associate="distance", delta=1.5, all=all_pairs)
        ours = rpe(SE3(ref), SE3(est), stamps, stamps, pair_by="distance", delta=1.5,
                   all_pairs=all_pairs)
        assert float(ours.stats.mean) == pytest.approx(float(theirs["Mean"]), rel=1e-10)
        assert float(ours.stats.rmse) == pytest.approx(float(theirs["RMSE"]), rel=1e-10)


def test_epoch_second_stamps_keep_their_differences_without_x64():
    """TUM-style epoch seconds (1.6e9, float32 spacing 128 s) with x64 off, JAX's default:
    every stamp collapsed onto one float32 value, associate paired everything with pose 0
    and called it valid, and ape of a trajectory against itself (2 ms late) had RMSE 5.34.
    Host stamps are now shifted to a common origin first (numpy float64 reference)."""
    ref = 1.6e9 + np.arange(10) / 30.0
    late = ref + 0.002
    with jax.enable_x64(False):
        poses = SE3.exp(np.c_[np.arange(10.0), np.zeros((10, 5))].astype(np.float32))
        ri, ei, ok = associate(ref, late, max_diff=0.001)
        res = ape(poses, poses, ref, late, max_diff=0.01)
        ri_ns, _, ok_ns = associate(
            (1_600_000_000 * 10**9 + np.arange(10) * 33_333_333).astype(np.int64),
            (1_600_000_000 * 10**9 + np.arange(10) * 33_333_333 + 2_000_000).astype(np.int64),
            max_diff=1_000_000)
    j = np.abs(late[:, None] - ref[None, :]).argmin(1)
    np.testing.assert_array_equal(ri, j)
    np.testing.assert_array_equal(ei, np.arange(10))
    assert not np.any(ok)  # 2 ms > 1 ms
    np.testing.assert_array_equal(res.pairs, np.stack([np.arange(10)] * 2, -1))
    assert float(res.stats.rmse) == 0.0
    np.testing.assert_array_equal(ri_ns, np.arange(10))  # nanoseconds: 2 ms > 1 ms too
    assert not np.any(ok_ns)


def test_nanosecond_stamps_seconds_apart_are_not_paired_without_x64():
    """Integer nanoseconds 2³² ns (4.3 s) apart with x64 off: the shifted int64
    differences became int32 and wrapped, and associate called all 20 pairs valid (numpy:
    the nearest stamps are 2.39 s apart). They are now shifted exactly in int64 and handed
    over as floats."""
    ns0 = 1_700_000_000_000_000_000
    ref = ns0 + np.arange(20) * 100_000_000
    est = ref + 2**32
    with jax.enable_x64(False):
        _, _, valid = associate(ref, est, max_diff=50_000_000)
        far, _, ok_far = associate(ref, ref + 3 * 10**9, max_diff=50_000_000)
    assert not np.any(valid)
    assert not np.any(ok_far)
    np.testing.assert_array_equal(far, np.full(20, 19))  # 3 s after the last ref stamp
