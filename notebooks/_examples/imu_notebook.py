"""Build ``notebooks/imu_preintegration.ipynb`` from two example scripts, so the notebook
never diverges from them: the percent-format tutorial ``imu_preintegration.py``
(preintegration, bias correction, batches, dead reckoning and IMU + GPS fusion), followed
by the module script ``imu_calibration.py`` (learned IMU calibration) and a cell that
runs it. Uses the shared helpers of ``build_notebooks.py`` (install cell, percent-format
parsing, script extraction). ``tests/imu/test_examples.py`` checks that the committed
notebook equals what this builder produces. Run
``python notebooks/_examples/imu_notebook.py`` after editing either script.
"""

from __future__ import annotations

import json
import os
import sys
from typing import Any

if __package__ in (None, ""):
    sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))

from notebooks._examples import build_notebooks as nb

NAME = "imu_preintegration"
TITLE = "IMU preintegration, IMU + GPS fusion and learned IMU calibration"
RUN_CALIBRATION = nb.SMOKE + """
jax.config.update("jax_enable_x64", True)
tiny = {"steps": 60, "num_train": 4, "num_test": 2, "num_samples": 1000, "batch": 16}
hist = train(**(tiny if SMOKE else {}))  # full size: about a minute on a laptop CPU
loss = np.asarray(hist.loss)
print(f"{loss.size} Adam steps: loss {loss[:10].mean():.2e} -> {loss[-10:].mean():.2e}")
print(format_table(hist.table, 200 * DT))
plot(hist)"""


def notebook() -> dict[str, Any]:
    cells = [
        nb._cell("code", nb.INSTALL),
        nb._cell("markdown", f"# {TITLE}\n\n{nb.docstring(NAME)}"),
    ]
    cells += [nb._cell(kind, text) for kind, text in nb.percent_cells(NAME)]
    cells += [
        nb._cell("markdown", "## Learned IMU calibration\n\n" + nb.docstring("imu_calibration")),
        nb._cell("code", nb.script_code("imu_calibration")),
        nb._cell("code", RUN_CALIBRATION),
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


def render() -> str:
    return json.dumps(notebook(), indent=1, ensure_ascii=False) + "\n"


def path() -> str:
    return os.path.join(nb.NOTEBOOKS, f"{NAME}.ipynb")


def main() -> None:
    with open(path(), "w", encoding="utf-8") as fh:
        fh.write(render())
    print("wrote", path())


if __name__ == "__main__":
    main()
