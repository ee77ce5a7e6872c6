"""Smoke test for bench/lie_ops.py: it runs end to end at a tiny batch and the three
contestants agree (so the benchmark never rots). Peers that are missing are skipped."""

import re

import pytest

lie_ops = pytest.importorskip("bench.lie_ops")


def _agreement_rows(text: str) -> list[str]:
    section = text.split("## Agreement")[1]
    return [ln for ln in section.splitlines() if re.match(r"\| f\d \|", ln)]


def test_lie_ops_runs_and_contestants_agree():
    # f2 exercises exp, compose and log of every contestant, values and Jacobians; f3 the
    # group action. (All three functions at every size: python bench/lie_ops.py --quick.)
    text = lie_ops.main(["--quick", "--threads", "0", "--batches", "16", "--funcs", "f2"])
    assert "## Throughput" in text and "## Compile time" in text
    rows = _agreement_rows(text)
    assert len(rows) == 2  # f2 value and jac
    assert all(r.rstrip().endswith("| yes |") for r in rows), text
    text = lie_ops.main(["--quick", "--threads", "0", "--batches", "16", "--funcs", "f3",
                         "--kinds", "value"])
    rows = _agreement_rows(text)
    assert len(rows) == 1 and all(r.rstrip().endswith("| yes |") for r in rows), text


def test_bars_and_formatting():
    assert lie_ops.bar_for("value", 1_000) == 10.0
    assert lie_ops.bar_for("jac", 1_000_000) == 2.0
    assert lie_ops.bar_for("value", 100_000) == 1.0
    from bench._common import fmt_batch, fmt_rate, fmt_ratio, markdown_table

    assert fmt_batch(1_000_000) == "1e6" and fmt_batch(16) == "16"
    assert fmt_rate(1.3e6) == "1.30e6" and fmt_ratio(3.0, 1.5) == "2.0x"
    assert fmt_ratio(1.0, None) == "—" and fmt_ratio(0.97, 1.0) == "0.97x"
    table = markdown_table(["a", "b"], [["x", "1.0x"]])
    assert table.splitlines()[1] == "|---|---:|"


def test_quick_help_text_is_literal():
    # `--help` of learned_weights.py crashed: its --quick text says "30 %", which argparse
    # read as a format directive.
    from bench._common import parser

    assert "intel at 30 % only" in parser("doc", quick="intel at 30 % only").format_help()


def test_missing_peer_is_reported_not_faked():
    from bench._common import import_peer

    peer = import_peer("surely_not_an_installed_module_xyz")
    assert not peer.available and "not installed" in peer.label()


def test_registry_lists_every_script(capsys):
    from pathlib import Path

    from bench import run

    scripts = {p.stem for p in Path(run.HERE).glob("*.py")} - run.NOT_BENCHMARKS
    assert set(run.WORKLOADS) == scripts  # every script is registered, none is stale
    assert run.main(["--list"]) == 0
    out = capsys.readouterr().out
    for name, spec in run.WORKLOADS.items():
        assert f"python bench/{name}.py" in out and spec.title in out
    run.main(["--list", "--quick", "--only", "pgo"])
    assert "--max-steps 50" in capsys.readouterr().out


def test_common_cli_and_threads(monkeypatch):
    import os

    from bench import _common

    ap = _common.parser("Title line.\n\nMore.", workers=True)
    args = ap.parse_args([])
    assert (args.quick, args.out, args.threads, args.clock, args.timeout) == (
        False, None, _common.DEFAULT_THREADS, "wall", _common.WORKER_TIMEOUT)
    assert not hasattr(_common.parser(None, threads=False).parse_args([]), "threads")
    caps = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")
    # a private copy of the environment: the caps must not leak into later tests
    monkeypatch.setattr(os, "environ", {k: v for k, v in os.environ.items() if k not in caps})
    assert _common.early_threads(["--quick", "--threads", "3"]) == 3
    assert _common.early_threads(["--threads=2"]) == 2
    assert [os.environ[v] for v in caps] == ["3"] * 3  # setdefault: the first call wins
    os.environ.clear()
    assert _common.early_threads(["--threads", "0"]) == 0 and not os.environ


def test_spawn_worker_answer_failure_and_timeout():
    from bench._common import spawn_worker

    ok = spawn_worker(["-c", "from bench._common import worker_result; "
                       "print('noise'); worker_result({'a': 1})"], timeout=120)
    assert ok["a"] == 1 and ok["wall_s"] > 0
    bad = spawn_worker(["-c", "import sys; print('boom', file=sys.stderr); sys.exit(3)"],
                       timeout=120)
    assert bad == {"failed": "exit 3: boom"}
    slow = spawn_worker(["-c", "import time; time.sleep(30)"], timeout=1)
    assert slow == {"failed": "timed out after 1 s"}


def test_merge_keeps_other_sections(tmp_path, monkeypatch):
    """``--merge`` re-runs the selected workload and carries the others over verbatim,
    with the date each was measured; an old report without that column gets its date."""
    from bench import run

    old = run.render([
        run.Outcome("optim", ["py", "bench/optim.py"], "ok", 3.0, "Result: old optim 2x"),
        run.Outcome("pgo", ["py", "bench/pgo.py"], "ok", 4.0, "# PGO\n\nResult: pgo 1.5x\n\nbody"),
    ], quick=False, load=(0.5, 0.5))
    report = tmp_path / "RESULTS.md"
    report.write_text(old, encoding="utf-8")
    kept = run.previous_sections(old)
    assert set(kept) == {"optim", "pgo"}
    assert "## pgo" in kept["pgo"][1] and "body" in kept["pgo"][1]

    def fake_run_one(name, quick, timeout, log=None, args=None):
        return run.Outcome(name, ["py", f"bench/{name}.py"], "ok", 1.0, "Result: new optim 9x")

    monkeypatch.setattr(run, "run_one", fake_run_one)
    assert run.main(["--only", "optim", "--merge", "--out", str(report)]) == 0
    text = report.read_text(encoding="utf-8")
    assert "new optim 9x" in text and "old optim 2x" not in text
    assert "pgo 1.5x" in text and "body" in text  # kept verbatim
    assert text.index('<a id="optim">') < text.index('<a id="pgo">')  # registry order
    assert "--merge" in text


def test_set_overrides_arguments_and_the_report_is_written_after_each_script(tmp_path,
                                                                             monkeypatch):
    """``--set NAME=ARGS`` reaches that script alone; a run stopped from outside after the
    first script keeps its section (the report is rewritten after every script)."""
    from bench import run

    seen = {}

    def fake_run_one(name, quick, timeout, log=None, args=None):
        seen[name] = args
        if name == "pgo":
            raise KeyboardInterrupt  # stopped from outside during the second script
        return run.Outcome(name, run.command(name, quick, tmp_path / "x.md", args), "ok", 1.0,
                           "Result: optim ran")

    monkeypatch.setattr(run, "run_one", fake_run_one)
    report = tmp_path / "RESULTS.md"
    with pytest.raises(KeyboardInterrupt):
        run.main(["--only", "optim,pgo", "--set", "optim=--quick --batches 100,1000",
                  "--out", str(report)])
    assert seen == {"optim": ["--quick", "--batches", "100,1000"], "pgo": None}
    text = report.read_text(encoding="utf-8")
    assert "optim ran" in text and "--batches 100,1000" in text and '<a id="pgo">' not in text
    with pytest.raises(SystemExit, match="--set: expected NAME=ARGS"):
        run.main(["--set", "nosuchbench=--quick", "--out", str(report)])


def test_merge_keeps_the_earlier_section_when_the_rerun_times_out(tmp_path, monkeypatch):
    """A rerun that measured nothing (timeout, failure) must not erase the earlier result:
    the section stays, the summary row names the failure and the date of what was kept,
    and the rerun's last output lines (its rows so far) follow the section."""
    from bench import run

    old = run.render([run.Outcome("optim", ["py", "bench/optim.py"], "ok", 3.0,
                                  "# Optim\n\nResult: old optim 2x\n\n| row | 1 |")],
                     quick=False, load=(0.5, 0.5))
    report = tmp_path / "RESULTS.md"
    report.write_text(old, encoding="utf-8")

    def fake_run_one(name, quick, timeout, log=None, args=None):
        return run.Outcome(name, ["py", f"bench/{name}.py"], "timeout after 5 s", 5.0,
                           tail=["partial row | 0.9x"])

    monkeypatch.setattr(run, "run_one", fake_run_one)
    assert run.main(["--only", "optim", "--merge", "--out", str(report)]) == 1
    text = report.read_text(encoding="utf-8")
    assert "old optim 2x" in text and "| row | 1 |" in text
    summary = text.split("## Summary", 1)[1].split('<a id="', 1)[0]
    assert "timeout after 5 s on" in summary and "kept" in summary
    assert "Rerun on" in text and "partial row | 0.9x" in text
    # and the merged report parses again, keeping the section once
    again = run.previous_sections(text)
    assert again["optim"][1].count("old optim 2x") == 1


def test_timeout_keeps_what_the_script_printed(monkeypatch):
    import sys

    from bench import run

    script = "import time; print('row 1 | 0.9x', flush=True); time.sleep(60)"
    monkeypatch.setattr(run, "command", lambda *a, **k: [sys.executable, "-c", script])
    o = run.run_one("optim", False, timeout=3)
    assert o.status == "timeout after 3 s"
    assert "row 1 | 0.9x" in o.tail


def _kabsch_rmse(ref, est):
    """Independent reference: RMSE after the best rotation + translation (Horn/Kabsch)."""
    import numpy as np

    a, b = est - est.mean(0), ref - ref.mean(0)
    u, _, vt = np.linalg.svd(b.T @ a)
    d = np.ones(a.shape[1])
    d[-1] = np.sign(np.linalg.det(u @ vt))
    moved = a @ (u * d @ vt).T
    return float(np.sqrt(np.mean(np.sum((moved - b) ** 2, 1))))


@pytest.mark.parametrize("kind", ["SE2", "SE3"])
def test_outlier_bench_aligned_ape(kind):
    # the standard (whole-trajectory aligned) APE of bench/pgo_outliers.py: zero for a
    # rigidly moved copy, and the closed-form Kabsch RMSE for a deformed one, while the
    # first-pose APE also counts the drift
    import jax
    import numpy as np

    from jaxpose.lie import SO3

    jax.config.update("jax_enable_x64", True)
    pgo_outliers = pytest.importorskip("bench.pgo_outliers")
    rng = np.random.default_rng(0)
    n, dim = 40, 3 if kind == "SE3" else 2
    pos = np.cumsum(rng.normal(size=(n, dim)), 0)
    if kind == "SE3":
        q = rng.normal(size=(n, 4))
        ref = np.concatenate([pos, q / np.linalg.norm(q, axis=1, keepdims=True)], 1)
        c, s = np.cos(0.7), np.sin(0.7)
        rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        qz = [0.0, 0.0, np.sin(0.35), np.cos(0.35)]
        moved_q = np.asarray(SO3(np.asarray(qz)).compose(SO3(ref[:, 3:])).data)
        moved = np.concatenate([pos @ rot.T + [1.0, -2.0, 3.0], moved_q], 1)
    else:
        th = rng.uniform(-np.pi, np.pi, n)
        ref = np.concatenate([pos, np.cos(th)[:, None], np.sin(th)[:, None]], 1)
        c, s = np.cos(0.7), np.sin(0.7)
        rot = np.array([[c, -s], [s, c]])
        moved = np.concatenate([pos @ rot.T + [1.0, -2.0], np.cos(th + 0.7)[:, None],
                                np.sin(th + 0.7)[:, None]], 1)
    assert pgo_outliers.ape_aligned(kind, ref, moved) < 1e-9
    assert pgo_outliers.ape(kind, ref, moved) < 1e-9
    est = moved.copy()
    est[:, :dim] += np.linspace(0.0, 1.0, n)[:, None] * rng.normal(size=dim)  # drift
    expected = _kabsch_rmse(ref[:, :dim], est[:, :dim])
    assert pgo_outliers.ape_aligned(kind, ref, est) == pytest.approx(expected, rel=1e-9)
    assert pgo_outliers.ape(kind, ref, est) > expected


def test_time_jax_counts_the_optimised_program_only_when_asked():
    # bench/compile.py's deterministic size column: the lines of the compiled program's text
    import jax
    import jax.numpy as jnp

    from bench._common import time_jax

    def f(x):
        return jnp.sin(x) * 2.0 + jnp.cos(x)

    x = jnp.arange(8.0)
    timing, out = time_jax(f, x, repeats=1, min_time=0.0, hlo_lines=True)
    expected = jax.jit(f).lower(x).compile().as_text().count("\n")
    assert timing.hlo_lines == expected > 0
    assert jnp.allclose(out, f(x))
    assert time_jax(f, x, repeats=1, min_time=0.0)[0].hlo_lines is None


def test_outlier_bench_counts_draws_and_objectives():
    # --seeds: the summary counts lower / tie / higher by the 1 % tie rule and the cells
    # where jaxpose's TLS objective is at most GTSAM's (made-up results, no solve)
    pgo_outliers = pytest.importorskip("bench.pgo_outliers")

    def cell(ape_al, tls):
        return dict(ape=2 * ape_al, ape_pct=1.0, ape_al=ape_al, ape_al_pct=1.0, tls=tls)

    def draw(jp_ape, jp_tls):
        cells = {"outliers": 3, "jaxpose-gnc": cell(jp_ape, jp_tls),
                 "gtsam-gnc": cell(1.0, 100.0)}
        return {"g": {"extent": 10.0, "loops": 6, "rates": {0.5: cells}}}

    draws = {0: draw(0.5, 90.0), 1: draw(1.005, 100.0), 2: draw(1.5, 101.0)}
    args = pgo_outliers.build_parser().parse_args(["--contestants", "jaxpose-gnc,gtsam-gnc"])
    args.contestants = ["jaxpose-gnc", "gtsam-gnc"]
    text = pgo_outliers.draws_report(draws, args, ((0.0,) * 3, (0.0,) * 3))
    assert text.splitlines()[-1] == (
        "Result: over 3 cells jaxpose GNC is lower on 1, ties on 1, higher on 1 (aligned "
        "APE); its TLS objective is at most GTSAM's on 2 of 3")
    assert "| g | 50% | 0.5 / 1 (lower) | 1 / 1 (tie) | 1.5 / 1 (higher; GTSAM objective " \
           "lower) |" in text
    assert sum(line.startswith("Result:") for line in text.splitlines()) == 1


def test_compile_bench_peer_problem_derivatives_match_finite_differences():
    # bench/compile.py's side-by-side entries: jaxpose's implicit derivatives of the curve
    # fit against central differences of the converged fit (and optimistix's, if installed)
    import importlib.util

    import jax
    import jax.numpy as jnp
    import numpy as np

    from bench import compile as bench_compile

    jax.config.update("jax_enable_x64", True)
    loss, obs, direction = bench_compile._curve("jaxpose")
    along = jax.jit(lambda d: loss(obs + d * direction))
    h1, h2 = 1e-4, 3e-4  # O(h²) truncation ~1e-7 and ~1e-6 here (its third derivative is large)
    fd1 = (along(h1) - along(-h1)) / (2 * h1)
    fd2 = (along(h2) - 2 * along(0.0) + along(-h2)) / h2**2
    grad = jax.jit(jax.grad(loss))(obs)
    hess = jax.jit(jax.hessian(along))(jnp.zeros(()))
    assert float(jnp.dot(grad, direction)) == pytest.approx(float(fd1), rel=1e-6)
    assert float(hess) == pytest.approx(float(fd2), rel=1e-6)
    if importlib.util.find_spec("optimistix") is not None:
        peer_loss, _, _ = bench_compile._curve("optimistix")
        np.testing.assert_allclose(jax.jit(jax.grad(peer_loss))(obs), grad, rtol=1e-8,
                                   atol=1e-10)
