"""g2o reader/writer: real files, round trips, edges-only initialisation, malformed input."""

from __future__ import annotations

import functools
import pickle
import re
import warnings

import numpy as np
import pytest
from io_refs import data_file, pose_matrix, relative_matrix, write_text

from jaxpose.datasets import synthetic_pose_graph
from jaxpose.io import FormatError, PoseGraph, connected_components, read_g2o, write_g2o

# file -> (kind, vertices, edges); counts from ../shared/data/README.md (manhattan: ids 0..3499)
FILES = {
    "tinyGrid3D.g2o": ("SE3", 9, 11),
    "smallGrid3D.g2o": ("SE3", 125, 297),
    "parking-garage.g2o": ("SE3", 1661, 6275),
    "sphere2500.g2o": ("SE3", 2500, 4949),
    "sphere_bignoise_vertex3.g2o": ("SE3", 2200, 8647),
    "intel.g2o": ("SE2", 1728, 2512),
    "manhattan.g2o": ("SE2", 3500, 5453),
    "pose3example.txt": ("SE3", 5, 6),
    "pose2example.txt": ("SE2", 11, 12),
}


@functools.cache
def _read_cached(name: str) -> PoseGraph:
    return read_g2o(data_file("g2o", name))


def real(name: str) -> PoseGraph:
    data_file("g2o", name)  # skip (not cached) when the data are absent
    return _read_cached(name)


def assert_graphs_equal(a: PoseGraph, b: PoseGraph, poses_atol: float = 1e-15) -> None:
    assert a.kind == b.kind
    np.testing.assert_array_equal(a.vertex_ids, b.vertex_ids)
    np.testing.assert_array_equal(a.edges, b.edges)
    np.testing.assert_array_equal(a.fixed, b.fixed)
    np.testing.assert_allclose(a.poses, b.poses, rtol=1e-15, atol=poses_atol)
    np.testing.assert_allclose(a.measurements, b.measurements, rtol=1e-15, atol=poses_atol)
    np.testing.assert_array_equal(a.information, b.information)


# ----------------------------------------------------------------------------- real files


@pytest.mark.parametrize("name", FILES)
def test_reads_reference_files(name):
    kind, n, m = FILES[name]
    g = real(name)
    d, t = (7, 6) if kind == "SE3" else (4, 3)
    assert g.kind == kind and g.n_poses == n and g.n_edges == m
    assert g.poses.shape == (n, d) and g.measurements.shape == (m, d)
    assert g.information.shape == (m, t, t) and g.edges.shape == (m, 2)
    assert g.vertex_ids.dtype == np.int64 and g.edges.dtype == np.int64
    assert g.poses.dtype == np.float64 and g.information.dtype == np.float64
    assert g.edges.min() >= 0 and g.edges.max() < n
    assert g.fixed.shape == (0,)
    np.testing.assert_array_equal(g.information, np.swapaxes(g.information, -1, -2))
    np.linalg.cholesky(g.information)  # positive definite
    rot = slice(3, 7) if kind == "SE3" else slice(2, 4)
    np.testing.assert_allclose(np.linalg.norm(g.poses[:, rot], axis=1), 1, atol=1e-15)
    np.testing.assert_allclose(np.linalg.norm(g.measurements[:, rot], axis=1), 1, atol=1e-15)
    assert np.isfinite(g.poses).all() and g.path.endswith(name)


def _raw_rows(path, tag):
    return [line.split()[1:] for line in path.read_text().splitlines() if line.startswith(tag)]


def test_values_match_the_text():
    """Spot-check against an independent parse: SE3 quaternions, SE2 angles, information."""
    path = data_file("g2o", "parking-garage.g2o")
    g = real("parking-garage.g2o")
    v = np.array(_raw_rows(path, "VERTEX_SE3:QUAT"), float)
    q = v[:, 4:] / np.linalg.norm(v[:, 4:], axis=1, keepdims=True)
    np.testing.assert_array_equal(g.vertex_ids, v[:, 0].astype(int))
    np.testing.assert_array_equal(g.poses[:, :3], v[:, 1:4])
    np.testing.assert_allclose(g.poses[:, 3:], q, atol=1e-16)
    e = np.array(_raw_rows(path, "EDGE_SE3:QUAT"), float)
    iu = np.triu_indices(6)
    np.testing.assert_array_equal(g.information[:, iu[0], iu[1]], e[:, 9:])
    np.testing.assert_array_equal(g.information[:, iu[1], iu[0]], e[:, 9:])
    assert g.information[0, 3, 3] == 4.00073 and g.information[0, 3, 5] == 0.0691425

    path = data_file("g2o", "intel.g2o")
    g = real("intel.g2o")
    v = np.array(_raw_rows(path, "VERTEX_SE2"), float)
    np.testing.assert_allclose(np.arctan2(g.poses[:, 3], g.poses[:, 2]), v[:, 3], atol=1e-15)
    e = np.array(_raw_rows(path, "EDGE_SE2"), float)
    np.testing.assert_allclose(
        np.arctan2(g.measurements[:, 3], g.measurements[:, 2]), e[:, 4], atol=1e-15
    )
    assert g.information[0, 0, 2] == g.information[0, 2, 0] == -7.085  # I13


def test_manhattan_edges_only_initialisation():
    """No VERTEX lines: chained odometry reproduces every odometry measurement exactly."""
    g = real("manhattan.g2o")
    np.testing.assert_array_equal(g.vertex_ids, np.arange(3500))
    np.testing.assert_array_equal(g.poses[0], [0, 0, 1, 0])
    ids = g.vertex_ids[g.edges]
    odo = np.flatnonzero(ids[:, 1] == ids[:, 0] + 1)
    _, first = np.unique(ids[odo, 0], return_index=True)
    odo = odo[first]  # the first (k, k+1) edge of each k: the ones the chain follows
    assert len(odo) == 3499
    rel = relative_matrix("SE2", g.poses, g.edges[odo])
    np.testing.assert_allclose(rel, pose_matrix("SE2", g.measurements[odo]), atol=1e-10)
    assert connected_components(g).max() == 0


# ----------------------------------------------------------------------------- round trips


@pytest.mark.parametrize("name", ["tinyGrid3D.g2o", "intel.g2o", "manhattan.g2o"])
def test_round_trip_reference(tmp_path, name):
    g = real(name)
    write_g2o(tmp_path / "out.g2o", g)
    back = read_g2o(tmp_path / "out.g2o")
    assert_graphs_equal(g, back, poses_atol=1e-15 if g.kind == "SE3" else 2e-16 * 100)
    assert back.path == str(tmp_path / "out.g2o")


@pytest.mark.parametrize(
    "kind,shape", [("SE3", "sphere"), ("SE3", "grid"), ("SE2", "circle"), ("SE2", "grid")]
)
def test_round_trip_synthetic(tmp_path, kind, shape):
    g, gt = synthetic_pose_graph(kind, n_poses=60, noise=(0.05, 0.1), seed=3, shape=shape)
    # non-diagonal information and large angles exercise the upper-triangle and atan2 paths
    rng = np.random.default_rng(0)
    A = rng.normal(size=g.information.shape)
    info = A @ np.swapaxes(A, -1, -2) + np.eye(g.information.shape[-1])
    g = PoseGraph(g.kind, g.vertex_ids * 3 + 7, g.poses, g.edges, g.measurements, info)
    write_g2o(tmp_path / "g.g2o", g)
    back = read_g2o(tmp_path / "g.g2o")
    assert_graphs_equal(g, back, poses_atol=1e-15)
    if kind == "SE2":
        ang = lambda p: np.arctan2(p[:, 3], p[:, 2])
        np.testing.assert_allclose(ang(back.poses), ang(g.poses), rtol=0, atol=1e-15)
    # poses= overrides graph.poses (e.g. optimised poses) and the FIX lines survive
    g = PoseGraph(g.kind, g.vertex_ids, g.poses, g.edges, g.measurements, info, fixed=[0, 5])
    write_g2o(tmp_path / "opt.g2o", g, poses=gt)
    back = read_g2o(tmp_path / "opt.g2o")
    np.testing.assert_allclose(back.poses, gt, atol=1e-15)
    np.testing.assert_array_equal(back.fixed, [0, 5])


def test_write_accepts_groups_and_checks_shape(tmp_path):
    jax = pytest.importorskip("jax")
    import jaxpose as jp

    g, gt = synthetic_pose_graph("SE3", n_poses=10, noise=(0.01, 0.01))
    with jax.enable_x64(True):
        write_g2o(tmp_path / "g.g2o", g, poses=jp.SE3(gt))
    np.testing.assert_allclose(read_g2o(tmp_path / "g.g2o").poses, gt, atol=1e-15)
    with pytest.raises(ValueError, match=r"poses must have shape \(10, 7\)"):
        write_g2o(tmp_path / "g.g2o", g, poses=gt[:, :4])


# ----------------------------------------------------------------------------- parsing details

I6 = "1 0 0 0 0 0 1 0 0 0 0 1 0 0 0 1 0 0 1 0 1"  # upper triangle of the 6x6 identity
I3 = "1 0 0 1 0 1"


def V3(i, q="0 0 0 1"):
    return f"VERTEX_SE3:QUAT {i} 0 0 0 {q}"


def E3(i, j, t="1 0 0", q="0 0 0 1", info=I6):
    return f"EDGE_SE3:QUAT {i} {j} {t} {q} {info}"


def V2(i, x="0 0 0"):
    return f"VERTEX_SE2 {i} {x}"


def E2(i, j, z="1 0 0", info=I3):
    return f"EDGE_SE2 {i} {j} {z} {info}"


def test_ids_are_mapped_to_file_order_indices(tmp_path):
    lines = ["# comment", "", V2(10, "1 2 0.5"), V2(4), "FIX 10", V2(7), E2(7, 10), E2(4, 7)]
    g = read_g2o(write_text(tmp_path, lines))
    np.testing.assert_array_equal(g.vertex_ids, [10, 4, 7])
    np.testing.assert_array_equal(g.edges, [[2, 0], [1, 2]])
    np.testing.assert_array_equal(g.fixed, [0])
    np.testing.assert_allclose(g.poses[0], [1, 2, np.cos(0.5), np.sin(0.5)])


def test_quaternions_are_normalised_and_crlf_is_fine(tmp_path):
    path = tmp_path / "crlf.g2o"
    path.write_bytes(
        f"{V3(0, '0 0 0 2')}\r\n{V3(1, '1 1 1 1')}\r\n{E3(0, 1, q='0 0 3 4')}\r\n".encode()
    )
    g = read_g2o(path, kind="SE3")
    np.testing.assert_allclose(g.poses[:, 3:], [[0, 0, 0, 1], [0.5, 0.5, 0.5, 0.5]])
    np.testing.assert_allclose(g.measurements[0, 3:], [0, 0, 0.6, 0.8])


def test_fix_lines(tmp_path):
    g = read_g2o(write_text(tmp_path, [V2(3), V2(1), "FIX 1 3", "FIX 1", E2(3, 1)]))
    np.testing.assert_array_equal(g.fixed, [1, 0])  # indices, first appearance, no repeats
    g = read_g2o(write_text(tmp_path, [E2(5, 6), "FIX 6"]))  # edges-only: ids from edges
    np.testing.assert_array_equal(g.fixed, [1])


@pytest.mark.parametrize("kind", ["SE2", "SE3"])
def test_fix_lines_are_written_after_the_edges(tmp_path, kind):
    """GTSAM's 2-D readG2o stops at the first line it does not know: with FIX lines
    between the vertices and the edges it read an SE2 graph of 35 edges as none."""
    graph, _ = synthetic_pose_graph(kind, 20, seed=0)
    assert graph.fixed.size
    path = tmp_path / "fixed.g2o"
    write_g2o(path, graph)
    tags = [line.split()[0] for line in path.read_text().splitlines()]
    first_fix = tags.index("FIX")
    assert all(t == "FIX" for t in tags[first_fix:]) and tags[first_fix - 1].startswith("EDGE")
    back = read_g2o(path)
    np.testing.assert_array_equal(back.fixed, graph.fixed)
    gtsam = pytest.importorskip("gtsam")
    factors, values = gtsam.readG2o(str(path), kind == "SE3")
    assert values.size() == 20 and factors.size() == graph.n_edges


def test_unknown_tags_warn_and_are_skipped(tmp_path):
    lines = [V2(0), V2(1), "VERTEX_XY 2 1 1", "EDGE_SE2_XY 0 2 1 1 1 0 1", E2(0, 1), "PARAMS x"]
    with pytest.warns(UserWarning, match=r"VERTEX_XY \(1x, first on line 3\)"):
        g = read_g2o(write_text(tmp_path, lines))
    assert g.n_poses == 2 and g.n_edges == 1


def test_vertices_without_edges(tmp_path):
    g = read_g2o(write_text(tmp_path, [V3(0), V3(1)]))
    assert g.edges.shape == (0, 2) and g.information.shape == (0, 6, 6)
    assert g.measurements.shape == (0, 7)


def test_edges_only_bfs_and_pieces(tmp_path):
    """Odometry first, then BFS over any edge (backwards uses Z⁻¹); extra pieces warn."""
    z = {(0, 1): "1 0 0.3", (3, 1): "0.5 -2 1.2", (3, 4): "2 1 -0.4", (7, 8): "1 1 1"}
    lines = [E2(i, j, v) for (i, j), v in z.items()]
    with pytest.warns(UserWarning, match="2 disconnected pieces"):
        g = read_g2o(write_text(tmp_path, lines))
    np.testing.assert_array_equal(g.vertex_ids, [0, 1, 3, 4, 7, 8])
    np.testing.assert_allclose(
        relative_matrix("SE2", g.poses, g.edges), pose_matrix("SE2", g.measurements), atol=1e-14
    )
    np.testing.assert_array_equal(g.poses[[0, 4]], [[0, 0, 1, 0]] * 2)  # each piece's start
    np.testing.assert_array_equal(connected_components(g), [0, 0, 0, 0, 1, 1])


def test_edges_only_prefers_odometry_over_loop_closures(tmp_path):
    """Vertex 2 is reached through the odometry chain 0→1→2, not the loop closure 0→2."""
    lines = [E3(0, 2, t="5 5 5"), E3(0, 1), E3(1, 2)]
    g = read_g2o(write_text(tmp_path, lines))
    np.testing.assert_allclose(g.poses[:, :3], [[0, 0, 0], [1, 0, 0], [2, 0, 0]])


# ----------------------------------------------------------------------------- malformed input

NPD = "1 2 0 1 0 1"  # [[1,2,0],[2,1,0],[0,0,1]]: eigenvalue −1
PSD6 = "1 0 0 0 0 0 1 0 0 0 0 1 0 0 0 0 0 0 0 0 0"  # rotation block zero

BAD = {
    "vertex token count": ([V3(0), "VERTEX_SE3:QUAT 1 0 0 0 0 0 1"], 2, "expected 8 values"),
    "edge token count": ([V2(0), V2(1), "EDGE_SE2 0 1 1 0 0 1 0 0 1 0"], 3, "found 10"),
    "se3 edge token count": ([V3(0), V3(1), E3(0, 1, info="1 0")], 3, "expected 30 values"),
    "non-numeric value": (
        [V2(0), V2(1), E2(0, 1, "1.0 abc 0")],
        3,
        "EDGE_SE2: expected a number for dy, found 'abc'",
    ),
    "non-integer id": (
        [V2(0), "VERTEX_SE2 1.5 0 0 0"],
        2,
        "VERTEX_SE2: expected an integer for id, found '1.5'",
    ),
    "non-integer edge id": (
        [V2(0), V2(1), E2("0", "x1")],
        3,
        "EDGE_SE2: expected an integer for j, found 'x1'",
    ),
    "missing vertex": ([V2(0), V2(1), E2(0, 1), E2(1, 7)], 4, "expected vertex 7"),
    "duplicate id": ([V2(0), "# c", V2(1), V2(0)], 4, "first defined on line 1"),
    "not positive definite": ([V2(0), V2(1), E2(0, 1), E2(1, 0, info=NPD)], 4, "(edge 1)"),
    "semidefinite se3": ([V3(0), V3(1), E3(0, 1, info=PSD6)], 3, "positive definite"),
    "nan measurement": ([V2(0), V2(1), E2(0, 1, "nan 0 0")], 3, "finite value for dx"),
    "inf vertex": ([V3(0), "VERTEX_SE3:QUAT 1 0 -inf 0 0 0 0 1"], 2, "finite value for y"),
    "nan information": ([V2(0), V2(1), E2(0, 1, info="1 0 0 nan 0 1")], 3, r"I\[y,y\]"),
    "zero quaternion vertex": ([V3(0, "0 0 0 0")], 1, "non-zero quaternion"),
    "zero quaternion edge": ([V3(0), V3(1), E3(0, 1, q="0 0 0 0")], 3, "non-zero quaternion"),
    "mixed kinds": ([V2(0), V3(1)], 2, "line 1 has VERTEX_SE2"),
    "mixed edges only": ([E2(0, 1), E3(1, 2)], 2, "SE2 and SE3 mixed"),
    "no pose lines": (["# only a comment", "FOO 1"], 2, "found none"),
    "fix missing vertex": ([V2(0), "FIX 5", V2(1)], 2, "expected vertex 5 to be defined by a"),
    "fix missing edges only": ([E2(0, 1), "FIX 9"], 2, "defined by an edge"),
    "fix without id": ([V2(0), "FIX"], 2, "found no id"),
    "fix non-integer": ([V2(0), "FIX zero"], 2, "found 'zero'"),
    "edges-only missing ids are fine, bad info is not": ([E2(3, 4, info=NPD)], 1, "EDGE_SE2 3 4"),
}


@pytest.mark.parametrize("case", BAD)
def test_malformed_g2o(tmp_path, case):
    lines, line, fragment = BAD[case]
    path = write_text(tmp_path, lines)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with pytest.raises(FormatError, match=fragment) as info:
            read_g2o(path)
    assert info.value.line == line
    assert str(info.value).startswith(f"{path}:{line}: ")
    assert isinstance(info.value, ValueError)


def test_requested_kind_must_match(tmp_path):
    path = write_text(tmp_path, [V2(0), V2(1), E2(0, 1)])
    with pytest.raises(FormatError, match=re.escape("kind='SE3' was requested")) as info:
        read_g2o(path, kind="SE3")
    assert info.value.line == 1
    assert read_g2o(path, kind="SE2").kind == "SE2"
    with pytest.raises(ValueError, match="kind must be"):
        read_g2o(path, kind="se3")


def test_format_error_pickles():
    err = pickle.loads(pickle.dumps(FormatError("a.g2o", 3, "expected x, found y")))
    assert str(err) == "a.g2o:3: expected x, found y" and err.line == 3 and err.path == "a.g2o"


def test_pose_graph_validates_fields():
    ok = dict(
        kind="SE2",
        vertex_ids=np.arange(2),
        poses=np.tile([0.0, 0, 1, 0], (2, 1)),
        edges=[[0, 1]],
        measurements=[[1.0, 0, 1, 0]],
        information=np.eye(3)[None],
    )
    g = PoseGraph(**ok)
    assert g.edges.dtype == np.int64 and g.fixed.shape == (0,) and "n_poses=2" in repr(g)
    for change, msg in [
        ({"kind": "SE4"}, "kind"),
        ({"poses": np.zeros((2, 7))}, r"poses: expected shape \(2, 4\)"),
        ({"edges": [[0, 2]]}, r"indices must lie in \[0, 2\)"),
        ({"edges": [[0.0, 1.0]]}, "expected integers"),
        ({"information": np.eye(6)[None]}, "information"),
        ({"fixed": [5]}, "fixed"),
    ]:
        with pytest.raises(ValueError, match=msg):
            PoseGraph(**{**ok, **change})
