"""BAL reader/writer and camera model: real files, round trips, malformed input."""

from __future__ import annotations

import numpy as np
import pytest
from io_refs import bal_project, data_file, write_text

from jaxpose.datasets import synthetic_bal
from jaxpose.geometry import bal_project as jax_bal_project
from jaxpose.io import BALProblem, FormatError, read_bal, write_bal
from jaxpose.io._bal import _bal_project_numpy

FILES = {  # file -> (cameras, points, observations)
    "dubrovnik-1-1-pre.txt": (1, 1, 1),
    "dubrovnik-3-7-18-pre.txt": (3, 7, 18),
    "dubrovnik-3-7-pre.txt": (3, 7, 19),
}


def assert_problems_equal(a: BALProblem, b: BALProblem) -> None:
    for name in ("cameras", "points", "camera_index", "point_index", "observations"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
        assert getattr(a, name).dtype == getattr(b, name).dtype


@pytest.mark.parametrize("name", FILES)
def test_reads_reference_files(name, tmp_path):
    n_cam, n_pt, n_obs = FILES[name]
    p = read_bal(data_file("bal", name))
    assert (p.n_cameras, p.n_points, p.n_observations) == (n_cam, n_pt, n_obs)
    assert p.cameras.shape == (n_cam, 9) and p.points.shape == (n_pt, 3)
    assert p.observations.shape == (n_obs, 2) and p.camera_index.dtype == np.int64
    assert p.camera_index.max() < n_cam and p.point_index.max() < n_pt
    assert p.path.endswith(name)
    # independent values from the text: first observation and the first camera's focal length
    np.testing.assert_array_equal(p.observations[0], [-385.99, 387.12])
    assert p.cameras[0, 6] == 1.4300319432711681e03
    # the points are in front of the cameras that see them (P_z < 0 in BAL's convention)
    _, P = bal_project(p.cameras, p.points, p.camera_index, p.point_index)
    assert (P[:, 2] < 0).all()
    write_bal(tmp_path / "out.txt", p)
    assert_problems_equal(p, read_bal(tmp_path / "out.txt"))


def test_round_trip_synthetic_and_token_layout(tmp_path):
    problem, truth = synthetic_bal(n_cameras=6, n_points=40, obs_per_point=3, seed=2)
    for p in (problem, truth):
        write_bal(tmp_path / "p.txt", p)
        assert_problems_equal(p, read_bal(tmp_path / "p.txt"))
    # line breaks are not significant: all tokens on one line, or one per line
    tokens = (tmp_path / "p.txt").read_text().split()
    (tmp_path / "one.txt").write_text(" ".join(tokens))
    (tmp_path / "many.txt").write_text("\n\n".join(tokens) + "\n\n")
    assert_problems_equal(truth, read_bal(tmp_path / "one.txt"))
    assert_problems_equal(truth, read_bal(tmp_path / "many.txt"))


def test_numpy_bal_projection_matches_independent_model_and_geometry():
    rng = np.random.default_rng(0)
    cams = np.concatenate(
        [
            rng.normal(size=(5, 3)) * [[1], [1], [1e-9], [0], [2]],  # incl. tiny and zero angle
            rng.normal(size=(5, 3)) + [0, 0, -8],
            rng.uniform(300, 900, (5, 1)),
            rng.normal(scale=0.1, size=(5, 1)),
            rng.normal(scale=0.01, size=(5, 1)),
        ],
        1,
    )
    pts = rng.normal(size=(20, 3))
    ci, pi = rng.integers(0, 5, 60), rng.integers(0, 20, 60)
    ref, _ = bal_project(cams, pts, ci, pi)
    np.testing.assert_allclose(_bal_project_numpy(cams, pts, ci, pi), ref, rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(_bal_project_numpy(cams[ci], pts[pi]), ref, rtol=1e-12, atol=1e-9)
    # the host twin and the public (JAX) camera model are one model
    got = jax_bal_project(pts[pi], cams[ci])
    tol = 1e-9 if got.dtype == np.float64 else 1e-4
    np.testing.assert_allclose(got, ref, rtol=tol, atol=tol)


def test_bal_problem_validates_fields():
    ok = dict(
        cameras=np.zeros((1, 9)),
        points=np.zeros((2, 3)),
        camera_index=[0, 0],
        point_index=[0, 1],
        observations=np.zeros((2, 2)),
    )
    assert "n_points=2" in repr(BALProblem(**ok))
    for change, msg in [
        ({"cameras": np.zeros((1, 8))}, r"cameras: expected shape \(\*, 9\)"),
        ({"point_index": [0, 2]}, r"point_index: indices must lie in \[0, 2\)"),
        ({"camera_index": [0.0, 0.0]}, "expected integers"),
        ({"observations": np.zeros((3, 2))}, "observations"),
    ]:
        with pytest.raises(ValueError, match=msg):
            BALProblem(**{**ok, **change})


# ----------------------------------------------------------------------------- malformed input

CAM = ["0.01", "0.02", "0.03", "0.1", "0.2", "-5", "500", "0.01", "0.001"]
PT = ["0.1", "0.2", "0.3"]


def bal_lines(header="1 2 2", obs=("0 0 1.5 2.5", "0 1 -3 4"), cam=CAM, pts=PT + PT):
    return [header, *obs, *cam, *pts]


BAD = {
    # name: (lines, expected line, message fragment)
    "short header": (["1 2"], 1, "expected a header"),
    "non-integer header": (
        bal_lines(header="1 2.0 2"),
        1,
        "header: expected an integer for n_points, found '2.0'",
    ),
    "negative count": (bal_lines(header="1 2 -2"), 1, "non-negative n_observations"),
    "camera index out of range": (bal_lines(obs=("0 0 1 2", "1 1 3 4")), 3, "camera index"),
    "point index out of range": (bal_lines(obs=("0 0 1 2", "0 2 3 4")), 3, r"in \[0, 2\)"),
    "negative index": (bal_lines(obs=("0 -1 1 2", "0 1 3 4")), 2, "found -1"),
    "non-integer index": (bal_lines(obs=("0 0 1 2", "0 1.0 3 4")), 3, "integer point index"),
    "non-numeric observation": (
        bal_lines(obs=("0 0 1 2", "0 1 3 x4")),
        3,
        "observation 1: expected a number for v, found 'x4'",
    ),
    "nan observation": (bal_lines(obs=("0 0 nan 2", "0 1 3 4")), 2, "finite u"),
    "inf camera parameter": (
        bal_lines(cam=CAM[:6] + ["inf"] + CAM[7:]),
        10,
        "camera 0: expected a finite f",
    ),
    "non-numeric point": (
        bal_lines(pts=PT + ["0.1", "?", "0.3"]),
        17,
        "point 1: expected a number for y, found '[?]'",
    ),
    "truncated points": (bal_lines(pts=PT + ["0.1"]), 16, "expected 6 point coordinates"),
    "truncated observations": (["1 2 3", "0 0 1 2", "0 1 3 4"], 3, "expected 12 observations"),
    "extra values": (bal_lines() + ["7"], 19, "found more: '7'"),
    # a digit separator, and a g2o file given as BAL (was blamed on digit separators)
    "digit separator": (bal_lines(obs=("0 0 1_0 2", "0 1 3 4")), 2,
                        r"found '1_0' \('_' digit separators are not part of the format\)"),
    "g2o tag": (["VERTEX_SE2 0 0 0 0", "EDGE_SE2 0 1 1 0 0 1 0 0 1 0 1"], 1,
                r"found 'VERTEX_SE2' \(not a number\)"),
}


@pytest.mark.parametrize("case", BAD)
def test_malformed_bal(tmp_path, case):
    lines, line, fragment = BAD[case]
    path = write_text(tmp_path, lines, "bad.txt")
    with pytest.raises(FormatError, match=fragment) as info:
        read_bal(path)
    assert info.value.line == line
    assert str(info.value).startswith(f"{path}:{line}: ")


def test_good_minimal_file_reads(tmp_path):
    p = read_bal(write_text(tmp_path, bal_lines(), "good.txt"))
    np.testing.assert_array_equal(p.point_index, [0, 1])
    np.testing.assert_array_equal(p.observations, [[1.5, 2.5], [-3, 4]])
    assert p.cameras[0, 5] == -5 and p.points.shape == (2, 3)
