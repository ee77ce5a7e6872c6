"""`jaxpose pgo`: optimise tinyGrid3D, write the result and a plot, read it back;
`jaxpose ba`: bundle-adjust a BAL file, write it, check the minimum against SciPy."""

from __future__ import annotations

import re

import numpy as np

from jaxpose import read_g2o
from jaxpose.cli import main

from .conftest import GTSAM_COST, data_file, numpy_pose_graph_cost


def test_cli_pgo_tinygrid3d_writes_a_lower_cost_graph(tmp_path, capsys):
    src = data_file("tinyGrid3D.g2o")
    out, png = tmp_path / "o.g2o", tmp_path / "o.png"
    assert main(["pgo", str(src), "--out", str(out), "--plot", str(png), "--quiet"]) == 0
    text = capsys.readouterr().out
    assert f"wrote {png}" in text
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 10_000
    assert "iter " not in text  # --quiet: no per-iteration table
    m = re.search(r"initial cost (\S+)\s+final cost (\S+)\s+iterations (\d+)\s+status (\w+)", text)
    assert m, text
    assert m.group(4) == "converged" and int(m.group(3)) > 0
    before, after = read_g2o(src), read_g2o(out)
    # same graph, new poses; the gauge (first pose) unchanged
    np.testing.assert_array_equal(after.edges, before.edges)
    np.testing.assert_array_equal(after.vertex_ids, before.vertex_ids)
    np.testing.assert_allclose(after.measurements, before.measurements, rtol=0, atol=1e-15)
    np.testing.assert_allclose(after.information, before.information, rtol=0, atol=0)
    np.testing.assert_allclose(after.poses[0], before.poses[0], rtol=0, atol=1e-15)
    c0, c1 = numpy_pose_graph_cost(before), numpy_pose_graph_cost(after)
    assert c1 < c0
    np.testing.assert_allclose(c1, GTSAM_COST["tinyGrid3D.g2o"], rtol=1e-5)
    np.testing.assert_allclose(float(m.group(2)), c1, rtol=1e-6)  # printed with 7 digits
    # LM starts from the chordal initialisation (--init auto), computed in the compiled
    # solve for a graph this small; the host's chordal poses give the same initial cost
    from jaxpose.graph import chordal_initialization

    c_init = numpy_pose_graph_cost(before, chordal_initialization(before))
    assert c_init < c0
    assert "initialisation: chordal (in the compiled solve)" in text
    np.testing.assert_allclose(float(m.group(1)), c_init, rtol=1e-6)


def test_cli_pgo_holds_the_files_fix_vertex(tmp_path, capsys):
    """A FIX line is the file's gauge: that pose stays where it is (it moved while pose 0
    was held instead and OUT still said FIX 5), and the graph reaches its minimum."""
    import dataclasses

    from jaxpose import synthetic_pose_graph, write_g2o

    g, _ = synthetic_pose_graph("SE2", n_poses=10, seed=2, noise=(0.05, 0.1))
    g = dataclasses.replace(g, fixed=np.array([5]))
    src, out = tmp_path / "fix5.g2o", tmp_path / "out.g2o"
    write_g2o(src, g)
    assert main(["pgo", str(src), "--out", str(out), "--quiet"]) == 0
    assert "status converged" in capsys.readouterr().out
    before, after = read_g2o(src), read_g2o(out)
    np.testing.assert_array_equal(after.fixed, [5])
    np.testing.assert_allclose(after.poses[5], before.poses[5], rtol=0, atol=1e-15)
    assert np.abs(after.poses[0] - before.poses[0]).max() > 1e-3  # pose 0 is free
    assert numpy_pose_graph_cost(after) < numpy_pose_graph_cost(before)


def test_cli_pgo_initialises_on_the_host_above_the_dense_size(capsys):
    """smallGrid3D (125 poses, 750 tangent dimensions: above what the in-solve relaxation
    takes) is initialised on the host, its time and the host relaxation's cost printed;
    LM then reaches GTSAM's cost."""
    src = data_file("smallGrid3D.g2o")
    assert main(["pgo", str(src), "--quiet"]) == 0
    text = capsys.readouterr().out
    m = re.search(r"initialisation: chordal \(\S+ s\), cost (\S+)", text)
    assert m, text
    from jaxpose.graph import chordal_initialization

    before = read_g2o(src)
    c_init = numpy_pose_graph_cost(before, chordal_initialization(before))
    np.testing.assert_allclose(float(m.group(1)), c_init, rtol=1e-6)
    m = re.search(r"final cost (\S+)", text)
    np.testing.assert_allclose(float(m.group(1)), GTSAM_COST["smallGrid3D.g2o"], rtol=1e-5)


def test_cli_ba_fixed_intrinsics_reaches_scipy_minimum(tmp_path, capsys):
    from jaxpose.io import read_bal

    from .conftest import DATA
    from .test_ba import _project, _scipy_minimum

    src = DATA / "bal" / "dubrovnik-3-7-pre.txt"
    if not src.is_file():
        import pytest

        pytest.skip(f"reference data {src} not present")
    out = tmp_path / "o.txt"
    assert main(["ba", str(src), "--fix-intrinsics", "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "graph.solve iter    1" in text and "status converged" in text
    before, after = read_bal(src), read_bal(out)
    np.testing.assert_array_equal(after.cameras[:, 6:], before.cameras[:, 6:])
    np.testing.assert_array_equal(after.observations, before.observations)
    cost = 0.5 * np.sum((_project(after.cameras, after.points, after.camera_index,
                                  after.point_index) - after.observations) ** 2)
    np.testing.assert_allclose(cost, _scipy_minimum(before), rtol=1e-8)
    m = re.search(r"reprojection RMSE (\S+) -> (\S+) px", text)
    np.testing.assert_allclose(float(m.group(2)), np.sqrt(cost / before.n_observations),
                               rtol=1e-3)
    assert main(["ba", str(tmp_path / "missing.txt")]) == 1
    assert "jaxpose ba:" in capsys.readouterr().err
