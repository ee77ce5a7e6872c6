"""The notebooks' example scripts: smoke runs at tiny sizes (default) and the full
acceptance runs (slow); the committed notebooks must equal what the builder produces."""

import io
import json
import os
from contextlib import redirect_stdout

import numpy as np
import pytest

from notebooks._examples import build_notebooks, cartpole_ilqr, mpc_imitation

NB_DIR = os.path.dirname(build_notebooks.HERE)


@pytest.mark.parametrize("name", sorted(build_notebooks.SPECS))
def test_notebook_is_built_from_its_script(name):
    path = os.path.join(NB_DIR, f"{name}.ipynb")
    with open(path, encoding="utf-8") as fh:
        text = fh.read()
    assert text == build_notebooks.render(name), (
        f"{path} is stale: run python notebooks/_examples/build_notebooks.py"
    )
    nb = json.loads(text)
    assert nb["nbformat"] == 4
    first = "".join(nb["cells"][0]["source"])
    assert nb["cells"][0]["cell_type"] == "code"
    assert "pip install" in first and "git+" in first and "-e .." in first


def test_imitation_smoke():
    hist = mpc_imitation.train(steps=40, lr=3e-2)
    tl, ml = np.asarray(hist.traj_loss), np.asarray(hist.model_loss)
    assert tl.shape == (40,) and ml.shape == (41,)
    assert np.all(np.isfinite(tl)) and np.all(np.isfinite(ml))
    assert tl[-10:].mean() < 0.5 * tl[:10].mean()
    assert ml[-1] < ml[0]


@pytest.mark.slow
def test_imitation_recovers_expert_dynamics():
    hist = mpc_imitation.train(steps=3000, lr=3e-2)
    ml = np.asarray(hist.model_loss)
    assert ml[0] / ml[-1] >= 1e3, f"model loss fell only {ml[0] / ml[-1]:.1f}x"
    np.testing.assert_allclose(hist.A, hist.expert.A, atol=1e-2)
    np.testing.assert_allclose(hist.B, hist.expert.B, atol=1e-2)


@pytest.mark.slow
def test_imitation_unrolled_gradient_also_learns():
    hist = mpc_imitation.train(steps=300, lr=3e-2, gradient="unroll")
    ref = mpc_imitation.train(steps=300, lr=3e-2, gradient="implicit")
    np.testing.assert_allclose(hist.model_loss, ref.model_loss, rtol=1e-6)


def test_cartpole_example_smoke():
    out = io.StringIO()
    with redirect_stdout(out):
        sol = cartpole_ilqr.main(["--max-iter", "3"])
    assert "max_steps after 3 iterations" in out.getvalue()
    assert np.all(np.abs(np.asarray(sol.u)) <= 5.0)


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(build_notebooks.SPECS))
def test_notebook_executes(name):
    """Run the notebook's code cells (minus the install cell; plotting stubbed when
    matplotlib is missing)."""
    nb = build_notebooks.notebook(name)
    code = [("".join(c["source"])) for c in nb["cells"] if c["cell_type"] == "code"][1:]
    ns: dict = {"__name__": f"nb_{name}"}
    exec(compile(code[0], f"{name}.ipynb[script]", "exec"), ns)
    try:
        import matplotlib

        matplotlib.use("Agg")
    except ImportError:
        ns["plot"] = lambda *a, **k: None
    with redirect_stdout(io.StringIO()):
        exec(compile(code[1], f"{name}.ipynb[run]", "exec"), ns)
