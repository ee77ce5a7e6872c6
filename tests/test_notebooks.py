"""Every tutorial notebook in notebooks/ executes top to bottom (nbclient, a fresh IPython
kernel per notebook) at the tiny sizes selected by ``JAXPOSE_NOTEBOOK_SMOKE=1``, so the
tutorials never rot (XLA's fast-compile options come from tests/conftest.py); and every
notebook is Colab-ready (its first cell installs jaxpose only when it is not importable).

A notebook that needs an optional package declares it in its metadata,
``{"jaxpose": {"requires": ["mujoco"]}}``; it is skipped when that package is missing.
Skipped as a whole when nbclient / ipykernel are not installed (``pip install .[test]``).
"""

from __future__ import annotations

import importlib.util
import json
import os
import time
from pathlib import Path

import pytest

NOTEBOOK_DIR = Path(__file__).resolve().parents[1] / "notebooks"
NOTEBOOKS = sorted(NOTEBOOK_DIR.glob("*.ipynb"))
CELL_TIMEOUT = 600  # seconds; the smoke sizes take a few seconds per cell


def _load(path: Path) -> dict:
    with open(path, encoding="utf-8") as fh:
        return json.load(fh)


def test_notebooks_found():
    names = {p.stem for p in NOTEBOOKS}
    for expected in ("lie_groups", "least_squares", "pose_graph", "mpc_imitation"):
        assert expected in names


@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda p: p.stem)
def test_notebook_is_colab_ready(path):
    nb = _load(path)
    assert nb["nbformat"] == 4
    first = nb["cells"][0]
    src = "".join(first["source"])
    assert first["cell_type"] == "code", f"{path.name}: the first cell must install jaxpose"
    assert "pip" in src and "install" in src, f"{path.name}: first cell does not install"
    assert 'find_spec("jaxpose") is None' in src, (
        f"{path.name}: the install cell must only install when jaxpose is not importable"
    )
    for cell in nb["cells"]:
        if cell["cell_type"] == "code":
            assert not cell.get("outputs"), f"{path.name}: commit notebooks without outputs"
    code = "\n".join("".join(c["source"]) for c in nb["cells"] if c["cell_type"] == "code")
    assert "JAXPOSE_NOTEBOOK_SMOKE" in code, (
        f"{path.name}: read JAXPOSE_NOTEBOOK_SMOKE to shrink sizes for CI"
    )


@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda p: p.stem)
def test_notebook_executes(path, monkeypatch):
    nbformat = pytest.importorskip("nbformat")
    nbclient = pytest.importorskip("nbclient")
    pytest.importorskip("ipykernel")
    nb = nbformat.read(path, as_version=4)
    for module in nb.metadata.get("jaxpose", {}).get("requires", []):
        if importlib.util.find_spec(module.split(".")[0]) is None:
            pytest.skip(f"{path.name} needs {module}")
    monkeypatch.setenv("JAXPOSE_NOTEBOOK_SMOKE", "1")
    monkeypatch.setenv("PYDEVD_DISABLE_FILE_VALIDATION", "1")  # quiet debugger warning
    client = nbclient.NotebookClient(
        nb,
        timeout=CELL_TIMEOUT,
        # a loaded machine (CI's 2 cores, parallel workers) can take over nbclient's
        # defaults to start a kernel (60 s) or to deliver a cell's output after its reply
        # (4 s; a dropped output reads as "printed nothing"); two notebooks failed once
        # each under heavy load and passed on every rerun
        startup_timeout=CELL_TIMEOUT,
        iopub_timeout=60,
        kernel_name="python3",
        resources={"metadata": {"path": str(NOTEBOOK_DIR)}},
    )
    t0 = time.perf_counter()
    try:
        client.execute()
    except nbclient.exceptions.CellExecutionError as err:
        pytest.fail(f"{path.name} failed:\n{err}")
    elapsed = time.perf_counter() - t0
    outputs = [o for c in nb.cells if c.cell_type == "code" for o in c.get("outputs", [])]
    assert not [o for o in outputs if o.get("output_type") == "error"]
    printed = "".join(o.get("text", "") for o in outputs if o.get("output_type") == "stream")
    assert printed.strip(), f"{path.name} printed nothing"
    print(f"{path.name}: {elapsed:.1f} s")  # shown with -s / -rA
    if os.environ.get("JAXPOSE_NOTEBOOK_OUT"):  # keep the executed notebook for inspection
        out = Path(os.environ["JAXPOSE_NOTEBOOK_OUT"]) / path.name
        out.parent.mkdir(parents=True, exist_ok=True)
        nbformat.write(nb, out)
