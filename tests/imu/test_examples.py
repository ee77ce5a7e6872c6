"""The IMU examples: the committed notebook equals what its builder produces; the learned
calibration (``notebooks/_examples/imu_calibration.py``) at tiny settings trains through
the preintegrator and improves on raw preintegration; the full runs (slow) meet the
acceptance numbers. The tutorial notebook itself runs in ``tests/test_notebooks.py``."""

import io
import json
from contextlib import redirect_stdout

import numpy as np
import pytest

from notebooks._examples import imu_calibration, imu_notebook


def test_notebook_is_built_from_its_scripts():
    with open(imu_notebook.path(), encoding="utf-8") as fh:
        text = fh.read()
    assert text == imu_notebook.render(), (
        "notebooks/imu_preintegration.ipynb is stale: run python notebooks/_examples/"
        "imu_notebook.py"
    )
    nb = json.loads(text)
    first = "".join(nb["cells"][0]["source"])
    assert nb["cells"][0]["cell_type"] == "code" and "pip" in first
    code = "\n".join("".join(c["source"]) for c in nb["cells"] if c["cell_type"] == "code")
    assert "JAXPOSE_NOTEBOOK_SMOKE" in code and "def train(" in code


def test_calibration_smoke():
    """Tiny settings: the loss falls and the learned correction beats raw preintegration
    in rotation and position on held-out trajectories; the oracle is better still."""
    hist = imu_calibration.train(steps=80, num_train=4, num_test=2, num_samples=800,
                                 batch=16)
    loss = np.asarray(hist.loss)
    assert loss.shape == (80,) and np.all(np.isfinite(loss))
    assert loss[-10:].mean() < 0.2 * loss[:10].mean()
    raw, learned = hist.table["raw preintegration"], hist.table["learned correction"]
    oracle = hist.table["oracle (true model inverted)"]
    assert learned[0] < raw[0] and learned[1] < 0.5 * raw[1], hist.table
    assert oracle[0] < 0.1 * raw[0] and oracle[1] < 0.1 * raw[1]
    text = imu_calibration.format_table(hist.table, 1.0)
    assert text.count("\n") == 4 and "| raw preintegration |" in text
    # the simulated ground truth is consistent with the integrator: integrating the true
    # (error-free) signals of each test window from its true start reproduces its end
    w = hist.test
    rot, pos = imu_calibration._window_errors(w.gyro_true, w.acc_true, w)
    assert float(np.max(rot)) < 1e-9 and float(np.max(pos)) < 1e-9


@pytest.mark.slow
def test_calibration_full_cuts_errors():
    out = io.StringIO()
    with redirect_stdout(out):
        hist = imu_calibration.main([])
    raw, learned = hist.table["raw preintegration"], hist.table["learned correction"]
    assert learned[0] < 0.1 * raw[0] and learned[1] < 0.1 * raw[1], hist.table
    assert "| learned correction |" in out.getvalue()
