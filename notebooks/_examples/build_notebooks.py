"""Build the tutorial notebooks from the example scripts, so the two never diverge.

Each notebook is: a title and the script's docstring (markdown), the install cell (Colab:
from GitHub; inside a checkout: the checkout), the script's code verbatim (without its
``sys.path`` set-up and ``__main__`` block), and a cell that runs it at notebook size and
plots. ``tests/control/test_examples.py`` checks that the committed notebooks equal what
this builder produces. Run ``python notebooks/_examples/build_notebooks.py`` after editing
an example.
"""

from __future__ import annotations

import json
import os
import re
from typing import Any

HERE = os.path.dirname(os.path.abspath(__file__))
NOTEBOOKS = os.path.dirname(HERE)
REPO_URL = "https://github.com/jaxpose/jaxpose"

INSTALL = f"""# Install jaxpose: from GitHub on Colab, or this checkout when run from notebooks/.
!pip install -q "git+{REPO_URL}" || pip install -q -e .."""

SPECS: dict[str, dict[str, Any]] = {
    "mpc_imitation": {
        "title": "Differentiable MPC: imitation learning of linear dynamics",
        "run": """jax.config.update("jax_enable_x64", True)
hist = train(steps=3000)  # ~20 s on a CPU, compilation included
ml = hist.model_loss
print(f"model loss {float(ml[0]):.2e} -> {float(ml[-1]):.2e}, {float(ml[0] / ml[-1]):.1e}x lower")
print("learned A:\\n", hist.A, "\\nexpert A:\\n", hist.expert.A)
plot(hist)""",
    },
    "cartpole_ilqr": {
        "title": "Cart-pole swing-up with iLQR and force limits",
        "run": """jax.config.update("jax_enable_x64", True)
sol, model = solve(horizon=80, u_max=5.0)
print(STATUS_NAMES[int(sol.status)], int(sol.iterations), "iterations; cost", float(sol.cost))
print("final state", sol.x[-1], "| force range", float(sol.u.min()), float(sol.u.max()))
plot(sol, dt=0.05)""",
    },
    "bicycle_filters": {
        "title": "EKF, UKF and particle filter on a kinematic bicycle",
        "run": """jax.config.update("jax_enable_x64", True)
mc = monte_carlo(runs=100, steps=80, num_particles=500)
print(format_summary(summary(mc), runs=100))
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


def notebook(name: str) -> dict[str, Any]:
    spec = SPECS[name]
    cells = [
        _cell("code", INSTALL),
        _cell("markdown", f"# {spec['title']}\n\n{docstring(name)}"),
        _cell("code", script_code(name)),
        _cell("code", spec["run"]),
    ]
    return {
        "cells": cells,
        "metadata": {
            "colab": {"provenance": []},
            "kernelspec": {"display_name": "Python 3", "language": "python", "name": "python3"},
            "language_info": {"name": "python"},
        },
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
