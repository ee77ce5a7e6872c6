"""The README's first command: `jaxpose demo` must run and print real results."""

import re
import subprocess
import sys

from jaxpose.cli import main


def test_demo_small_runs_and_reports_accurate_identities(capsys):
    code = main(["demo", "--batch", "16", "--throughput-batch", "1000", "--poses", "50",
                 "--steps", "60", "--pgo-poses", "40"])
    out = capsys.readouterr().out
    assert code == 0
    # one row per group, every error column small in float64
    rows = [line for line in out.splitlines()
            if re.match(r"^(SO3|SE3|Sim3|RxSO3|SO2|SE2)\s", line)]
    assert len(rows) == 6
    for row in rows:
        errors = [float(v) for v in row.split()[1:]]
        assert len(errors) == 4 and max(errors) < 1e-10, row
    distance = float(re.search(r"distance to the true pose ([0-9.e+-]+)", out).group(1))
    assert distance < 0.15  # noise σ = 0.2 over 50 samples: ≈ 0.07 expected
    # the pose graph: 40 poses, solved (lower cost, converged) with the per-iteration table
    assert "synthetic sphere, 40 poses" in out and "graph.solve iter    1" in out
    m = re.search(r"initial cost (\S+)\s+final cost (\S+)\s+iterations \d+\s+status (\w+)", out)
    assert m and m.group(3) == "converged" and float(m.group(2)) < 0.5 * float(m.group(1))


def test_cli_without_command_prints_help():
    proc = subprocess.run([sys.executable, "-m", "jaxpose.cli"], capture_output=True, text=True)
    assert proc.returncode == 2
    assert "demo" in proc.stdout
