"""Build ``notebooks/mjx_learning.ipynb`` from ``mjx_learning.py`` (the same layout as
``build_notebooks.py``: install cell, title and docstring, the script's code, a run cell),
with an install cell that also brings MuJoCo MJX (the ``mjx`` extra) and notebook metadata
``{"jaxpose": {"requires": ["mujoco", "mujoco.mjx"]}}`` so CI skips it without MuJoCo.
``tests/test_mjx.py`` checks that the committed notebook equals this output; run
``python notebooks/_examples/mjx_notebook.py`` after editing the example.
"""

from __future__ import annotations

import json
import os
import sys
from typing import Any

if __package__:
    from .build_notebooks import NOTEBOOKS, REPO_URL, SMOKE, _cell, docstring, script_code
else:  # run as a script
    sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
    from build_notebooks import NOTEBOOKS, REPO_URL, SMOKE, _cell, docstring, script_code

NAME = "mjx_learning"
TITLE = "MuJoCo MJX + jaxpose: learning physical parameters through an EKF"

INSTALL = f"""# Install jaxpose with MuJoCo MJX and matplotlib unless importable: from this checkout
# (`pip install -e ..`) when the notebook runs from notebooks/, else from GitHub (Colab).
import importlib.util
import os
import subprocess
import sys

if importlib.util.find_spec("jaxpose") is None or importlib.util.find_spec("mujoco") is None:
    in_checkout = os.path.exists(os.path.join("..", "pyproject.toml"))
    source = ["-e", "..[mjx,plot]"] if in_checkout else ["jaxpose[mjx,plot] @ git+{REPO_URL}"]
    subprocess.check_call([sys.executable, "-m", "pip", "install", "-q", *source])
    import site  # this kernel started before the install: read the new .pth files now

    site.main()
    importlib.invalidate_caches()"""

RUN = SMOKE + """
jax.config.update("jax_enable_x64", True)
if SMOKE:
    hist = train(steps=5, batch=2, horizon=20)
else:
    hist = train(steps=200, batch=4, horizon=150)  # about a minute on a CPU, compile included
print(format_table(hist))
plot(hist)"""


def notebook() -> dict[str, Any]:
    cells = [
        _cell("code", INSTALL),
        _cell("markdown", f"# {TITLE}\n\n{docstring(NAME)}"),
        _cell("code", script_code(NAME)),
        _cell("code", RUN),
    ]
    return {
        "cells": cells,
        "metadata": {
            "colab": {"provenance": []},
            "jaxpose": {"requires": ["mujoco", "mujoco.mjx"]},
            "kernelspec": {"display_name": "Python 3", "language": "python", "name": "python3"},
            "language_info": {"name": "python"},
        },
        "nbformat": 4,
        "nbformat_minor": 4,
    }


def render() -> str:
    return json.dumps(notebook(), indent=1, ensure_ascii=False) + "\n"


def main() -> None:
    path = os.path.join(NOTEBOOKS, f"{NAME}.ipynb")
    with open(path, "w", encoding="utf-8") as fh:
        fh.write(render())
    print("wrote", path)


if __name__ == "__main__":
    main()
