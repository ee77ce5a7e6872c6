"""Smoke test of `jaxpose pgo`: optimise tinyGrid3D, write the result, read it back."""

from __future__ import annotations

import re

import numpy as np

from jaxpose import read_g2o
from jaxpose.cli import main

from .conftest import GTSAM_COST, data_file, numpy_pose_graph_cost


def test_cli_pgo_tinygrid3d_writes_a_lower_cost_graph(tmp_path, capsys):
    src = data_file("tinyGrid3D.g2o")
    out = tmp_path / "o.g2o"
    assert main(["pgo", str(src), "--out", str(out), "--quiet"]) == 0
    text = capsys.readouterr().out
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
    np.testing.assert_allclose(float(m.group(1)), c0, rtol=1e-6)
