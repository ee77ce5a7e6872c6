"""Build the tutorial notebooks from the example scripts, so the two never diverge.

Two kinds of scripts:

* module scripts (functions plus a ``main``): the notebook is the install cell, a title and
  the script's docstring (markdown), the script's code verbatim (without its ``sys.path``
  set-up and ``__main__`` block), and a cell that runs it at notebook size and plots;
* tutorial scripts in the "percent" format (``"format": "percent"`` below): after the
  header (docstring, ``sys.path`` set-up), ``# %%`` starts a code cell and
  ``# %% [markdown]`` a markdown cell whose lines are ``#`` comments. The script runs
  top to bottom as the notebook does.

The install cell installs jaxpose only when it is not importable (from this checkout
when the notebook runs from ``notebooks/``, else from GitHub, e.g. on Colab). Every
notebook honours ``JAXPOSE_NOTEBOOK_SMOKE=1`` (tiny sizes; module scripts' run cells
start with ``SMOKE`` below), which ``tests/test_notebooks.py`` sets to execute all of them
with nbclient; a spec's ``"requires": ["mujoco"]`` lists optional packages, without which
that test skips the notebook. ``tests/control/test_examples.py`` checks that the committed
notebooks equal what this builder produces. Run
``python notebooks/_examples/build_notebooks.py`` after editing an example.
"""

from __future__ import annotations

import json
import os
import re
from typing import Any

HERE = os.path.dirname(os.path.abspath(__file__))
NOTEBOOKS = os.path.dirname(HERE)
REPO_URL = "https://github.com/jaxpose/jaxpose"

INSTALL = f"""# Install jaxpose (with matplotlib) unless it is importable: from this checkout
# (`pip install -e ..`) when the notebook runs from notebooks/, else from GitHub (Colab).
import importlib.util
import os
import subprocess
import sys

if importlib.util.find_spec("jaxpose") is None:
    in_checkout = os.path.exists(os.path.join("..", "pyproject.toml"))
    source = ["-e", "..[plot]"] if in_checkout else ["jaxpose[plot] @ git+{REPO_URL}"]
    subprocess.check_call([sys.executable, "-m", "pip", "install", "-q", *source])
    import site  # this kernel started before the install: read the new .pth files now

    site.main()
    importlib.invalidate_caches()"""

SMOKE = """import os

SMOKE = os.environ.get("JAXPOSE_NOTEBOOK_SMOKE") == "1"  # tiny sizes (CI runs every notebook)"""

SPECS: dict[str, dict[str, Any]] = {
    "lie_groups": {"title": "Lie groups and manifold calculus", "format": "percent"},
    "least_squares": {"title": "Least squares and robust kernels", "format": "percent"},
    "pose_graph": {"title": "Pose-graph optimisation", "format": "percent"},
    "fixed_lag_smoother": {"title": "Fixed-lag smoothing", "format": "percent"},
    "uncertainty": {"title": "Uncertainty: marginal covariances", "format": "percent"},
    "mpc_imitation": {
        "title": "Differentiable MPC: imitation learning of linear dynamics",
        "run": SMOKE + """
jax.config.update("jax_enable_x64", True)
hist = train(steps=40 if SMOKE else 3000)  # ~20 s on a CPU, compilation included
ml = hist.model_loss
print(f"model loss {float(ml[0]):.2e} -> {float(ml[-1]):.2e}, {float(ml[0] / ml[-1]):.1e}x lower")
print("learned A:\\n", hist.A, "\\nexpert A:\\n", hist.expert.A)
plot(hist)""",
    },
    "cartpole_ilqr": {
        "title": "Cart-pole swing-up with iLQR and force limits",
        "run": SMOKE + """
jax.config.update("jax_enable_x64", True)
sol, model = solve(horizon=80, u_max=5.0, max_iter=3 if SMOKE else 400)
print(Results.name_of(sol.status), int(sol.iterations), "iterations; cost", float(sol.cost))
print("final state", sol.x[-1], "| force range", float(sol.u.min()), float(sol.u.max()))
plot(sol, dt=0.05)""",
    },
    "learned_weights": {
        "title": "Learning to reject wrong loop closures, through graph.solve",
        "run": SMOKE + """
jax.config.update("jax_enable_x64", True)
# laps around a circle; 30 % of the loop closures are replaced by random edges
graph, _ = synthetic_pose_graph("SE2", n_poses=60 if SMOKE else 400, seed=0)
result = experiment(
    graph, 0.3, train_seeds=[0] if SMOKE else [0, 1, 2],
    test_seeds=[1000] if SMOKE else [1000, 1001], steps=3 if SMOKE else 60,
    scales=(1.0,) if SMOKE else SCALES, kernels=("cauchy",) if SMOKE else tuple(KERNELS),
)
print(report(result))
plot(result)""",
    },
    "bicycle_filters": {
        "title": "EKF, UKF and particle filter on a kinematic bicycle",
        "run": SMOKE + """
jax.config.update("jax_enable_x64", True)
runs = 4 if SMOKE else 100
mc = monte_carlo(runs=runs, steps=10 if SMOKE else 80, num_particles=50 if SMOKE else 500)
print(format_summary(summary(mc), runs=runs))
plot(mc)""",
    },
}


def script_code(name: str) -> str:
    """The example's code as it appears in the notebook."""
    with open(os.path.join(HERE, f"{name}.py"), encoding="utf-8") as fh:
        src = fh.read()
    src = re.sub(r'\A""".*?"""\n', "", src, flags=re.S)  # docstring → markdown cell
    src = re.sub(r'\nif __package__ in \(None, ""\):\n(    .*\n)+', "\n", src)
    src = re.sub(r'\n\nif __name__ == "__main__":\n(    .*\n)+\Z', "\n", src)
    src = src.replace("from __future__ import annotations\n", "")
    src = src.replace("import os\nimport sys\n", "").replace("import sys\n", "")
    src = re.sub(r"\n{3,}import ", "\n\nimport ", src)
    return src.strip() + "\n"


def docstring(name: str) -> str:
    with open(os.path.join(HERE, f"{name}.py"), encoding="utf-8") as fh:
        src = fh.read()
    m = re.match(r'\A"""(.*?)"""', src, flags=re.S)
    return m.group(1).strip() if m else ""


def _cell(kind: str, text: str) -> dict[str, Any]:
    lines = text.rstrip("\n").splitlines(keepends=True)  # as `ruff format` leaves cells
    cell: dict[str, Any] = {"cell_type": kind, "metadata": {}, "source": lines}
    if kind == "code":
        cell.update(execution_count=None, outputs=[])
    return cell


def percent_cells(name: str) -> list[tuple[str, str]]:
    """``(kind, text)`` of every cell of a percent-format script (header dropped)."""
    with open(os.path.join(HERE, f"{name}.py"), encoding="utf-8") as fh:
        src = fh.read()
    cells: list[tuple[str, str]] = []
    for block in re.split(r"^# %%", src, flags=re.M)[1:]:
        head, _, body = block.partition("\n")
        if head.strip() == "[markdown]":
            lines = [re.sub(r"^# ?", "", line) for line in body.strip("\n").splitlines()]
            cells.append(("markdown", "\n".join(lines)))
        else:
            cells.append(("code", body.strip("\n")))
    if not cells:
        raise ValueError(f"{name}.py: no '# %%' cells (percent format expected)")
    return cells


def notebook(name: str) -> dict[str, Any]:
    spec = SPECS[name]
    cells = [
        _cell("code", INSTALL),
        _cell("markdown", f"# {spec['title']}\n\n{docstring(name)}"),
    ]
    if spec.get("format") == "percent":
        cells += [_cell(kind, text) for kind, text in percent_cells(name)]
    else:
        cells += [_cell("code", script_code(name)), _cell("code", spec["run"])]
    metadata: dict[str, Any] = {
        "colab": {"provenance": []},
        "kernelspec": {"display_name": "Python 3", "language": "python", "name": "python3"},
        "language_info": {"name": "python"},
    }
    if spec.get("requires"):  # optional packages: tests/test_notebooks.py skips without them
        metadata["jaxpose"] = {"requires": list(spec["requires"])}
    return {
        "cells": cells,
        "metadata": metadata,
        "nbformat": 4,
        "nbformat_minor": 4,
    }


def render(name: str) -> str:
    return json.dumps(notebook(name), indent=1, ensure_ascii=False) + "\n"


def main() -> None:
    for name in SPECS:
        path = os.path.join(NOTEBOOKS, f"{name}.ipynb")
        with open(path, "w", encoding="utf-8") as fh:
            fh.write(render(name))
        print("wrote", path)


if __name__ == "__main__":
    main()
