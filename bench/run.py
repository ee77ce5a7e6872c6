"""Run every benchmark in bench/ side by side with the installed peers and collect the
tables into one markdown report (``bench/RESULTS.md``).

Each benchmark script runs in its own subprocess (``python bench/NAME.py ARGS --out
TMP.md``), so JIT caches, thread pools and peak memory never leak between them; its
markdown report (tables of times and ratios against PyPose / jaxlie / GTSAM, with
compile time and steady-state time separate) is copied into the report under its own
heading, after a summary of what ran. Missing peers are reported as skipped by the
scripts themselves; a script that fails or times out is listed with the tail of its
output, never dropped silently.

Workloads: the registry :data:`WORKLOADS` below (name, title, full and ``--quick``
arguments; every script takes the common ``--quick/--out/--threads`` of
:func:`bench._common.parser`), plus any other ``bench/*.py`` that appears later (run with
``--quick`` in quick mode when its ``--help`` offers it, and ``--out`` when offered —
otherwise its stdout is the report). ``--list`` prints the registry.

Usage::

    python -m bench [--quick] [--only lie_ops,optim] [--skip pgo] [--out bench/RESULTS.md]
                    [--merge] [--readme README.md] [--timeout 3600] [--list]
                    [--set "lie_ops=--batches 1000,1000000"]

``--merge`` re-runs only the selected workloads and keeps every other section (and its
summary row, with the date it was measured) of the existing report, so one benchmark can
be refreshed without re-running all of them.

``--set NAME=ARGS`` runs one script with other arguments than the registry's (an
accelerator run's sizes, say); the summary's *command* column shows what ran.

``--readme FILE`` also rewrites the block between ``<!-- bench-results:start -->`` and
``<!-- bench-results:end -->`` in FILE with the summary table (the README's results
section is generated, not hand-written).
"""

from __future__ import annotations

import argparse
import datetime as _dt
import os
import re
import shlex
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
NOT_BENCHMARKS = {"__init__", "__main__", "_common", "run"}
README_START = "<!-- bench-results:start -->"
README_END = "<!-- bench-results:end -->"


@dataclass(frozen=True)
class Spec:
    """One workload: a script ``bench/NAME.py``, its title and its full and quick argument
    lists (``--out`` is added); ``minutes``: its full run's time limit where it needs more
    than ``--timeout``."""

    title: str
    full: tuple[str, ...] = ()
    quick: tuple[str, ...] = ("--quick",)
    minutes: float = 0.0


# The registry, in run order; quick = a smoke run of minutes (see each script's --help).
WORKLOADS: dict[str, Spec] = {
    "lie_ops": Spec("Lie-group ops: jaxpose vs PyPose vs jaxlie",
                    quick=("--quick", "--batches", "1000,10000")),
    "optim": Spec("Least squares (InvNet): jaxpose vs PyPose LM",
                  quick=("--quick", "--batches", "10,100")),
    "sparse_chain": Spec("Banded least squares: dense vs coloured Jacobian and sparse JᵀJ",
                         quick=("--quick",)),
    "pgo": Spec("Pose-graph optimisation: jaxpose vs GTSAM",
                quick=("--files", "tinyGrid3D,smallGrid3D", "--repeats", "1",
                       "--max-steps", "50")),
    "control": Spec("MPC (imitation problem): jaxpose vs PyPose",
                    quick=("--quick", "--sizes", "4,16", "--batches", "1,16")),
    "sharding": Spec("Sharding: throughput vs device count"),
    "geometry": Spec("Geometry: kNN, ICP, EPnP: jaxpose vs PyPose"),
    "imu": Spec("IMU preintegration: jaxpose vs PyPose"),
    "ba": Spec("Bundle adjustment: jaxpose vs GTSAM"),
    "smoother": Spec("Fixed-lag smoother: jaxpose vs GTSAM iSAM2"),
    "marginals": Spec("Marginal covariances: jaxpose vs GTSAM"),
    "pgo_outliers": Spec("Pose graphs with outliers (GNC): jaxpose vs GTSAM"),
    "ekf_convention": Spec("EKF linearisation point: jaxpose vs PyPose"),
    "compile": Spec("Compile time of differentiated solves (cold); jaxpose vs optimistix",
                    quick=("--quick", "--only", "ls_solve,ls_grad")),
    "backward": Spec("Backward pass through graph.solve vs one forward LM iteration",
                     quick=("--quick",)),
    "learned_weights": Spec("Learned edge weights through graph.solve vs tuned kernels",
                            quick=("--quick",), minutes=150),  # ~18 min per sphere2500 rate
}
KNOWN = WORKLOADS  # earlier name

@dataclass
class Outcome:
    """What one script produced (``kept``: a section carried over from an earlier report
    by ``--merge``, with its summary row as it was)."""

    name: str
    command: list[str]
    status: str  # "ok", "failed (rc N)", "timeout after S s"
    seconds: float
    report: str = ""
    tail: list[str] = field(default_factory=list)
    measured: str = ""  # when it ran ("YYYY-MM-DD HH:MM")
    kept_row: list[str] | None = None
    kept_section: str = ""


def discover() -> list[str]:
    """Benchmark scripts present in bench/: the known ones in their order, then others."""
    present = {p.stem for p in HERE.glob("*.py")} - NOT_BENCHMARKS
    known = [n for n in WORKLOADS if n in present]
    return known + sorted(present - set(known))


def _help(name: str) -> str:
    proc = subprocess.run([sys.executable, str(HERE / f"{name}.py"), "--help"], cwd=ROOT,
                          capture_output=True, text=True, timeout=300)
    return proc.stdout


def command(name: str, quick: bool, out: Path, args: Sequence[str] | None = None
            ) -> list[str]:
    """The subprocess command for ``name``: its settings (``args`` in place of the
    registry's, when given) plus ``--out`` where offered."""
    spec = WORKLOADS.get(name)
    if args is not None:
        args, has_out = list(args), True
    elif spec is not None:
        args, has_out = list(spec.quick if quick else spec.full), True
    else:  # a script this runner does not know yet: ask its --help
        text = _help(name)
        args = ["--quick"] if quick and "--quick" in text else []
        has_out = "--out" in text
    return [sys.executable, str(HERE / f"{name}.py"), *args] + (
        ["--out", str(out)] if has_out else []
    )


def run_one(name: str, quick: bool, timeout: float, log=None,
            args: Sequence[str] | None = None) -> Outcome:
    """Run one script in a subprocess and collect its markdown report."""
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / f"{name}.md"
        cmd = command(name, quick, out, args)
        if log:
            log(f"[{time.strftime('%H:%M:%S')}] {name}: {' '.join(cmd[1:])}")
        t0 = time.perf_counter()
        try:
            proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True,
                                  timeout=timeout)
        except subprocess.TimeoutExpired as err:
            # what it printed before it was stopped (scripts print their rows as they go)
            text = [(x.decode(errors="replace") if isinstance(x, bytes) else (x or ""))
                    for x in (err.stdout, err.stderr)]
            return Outcome(name, cmd, f"timeout after {timeout:.0f} s",
                           time.perf_counter() - t0,
                           tail=text[0].splitlines()[-12:] + text[1].splitlines()[-8:])
        seconds = time.perf_counter() - t0
        report = out.read_text(encoding="utf-8") if out.is_file() else proc.stdout
    status = "ok" if proc.returncode == 0 else f"failed (rc {proc.returncode})"
    tail = [] if proc.returncode == 0 else (proc.stderr or proc.stdout).splitlines()[-8:]
    return Outcome(name, cmd, status, seconds, report.strip(), tail)


def keep_after_failure(o: Outcome, row: list[str], section: str) -> Outcome:
    """A ``--merge`` rerun that failed or timed out: the earlier section stays (a failed
    rerun measures nothing), its summary row says so, and the rerun's last lines follow."""
    row = list(row)
    when = row[SUMMARY_HEADER.index("measured")]
    row[SUMMARY_HEADER.index("status")] = f"{o.status} on {o.measured}; result of {when} kept"
    note = [f"Rerun on {o.measured}: {o.status}; the result above is from {when}."]
    if o.tail:
        note += ["", "Last lines of the rerun:", "", "```", *o.tail, "```"]
    return Outcome(o.name, o.command, o.status, o.seconds, tail=o.tail, measured=o.measured,
                   kept_row=row, kept_section=section + "\n\n" + "\n".join(note))


def demote(markdown: str, levels: int = 1) -> str:
    """Shift every ATX heading down ``levels`` levels (so a script's ``#`` title nests
    under the report's ``##`` section); text inside code fences is left alone."""
    lines, fenced = [], False
    for line in markdown.splitlines():
        if line.lstrip().startswith("```"):
            fenced = not fenced
        if not fenced and re.match(r"#{1,6} ", line):
            line = "#" * levels + line
        lines.append(line)
    return "\n".join(lines)


def headline(report: str) -> str:
    """The script's one-line result: its first line starting with ``Result:`` or ``Bar``
    (ratios against the peers and whether the issue's bar is met), '—' if none."""
    for line in report.splitlines():
        m = re.match(r"\s*(?:Result:|Bar\b:?)\s*(.*)", line)
        if m:
            return m.group(1).strip().replace("|", "/")
    return "—"


def summary_table(outcomes: Sequence[Outcome]) -> str:
    from bench._common import markdown_table

    rows = []
    for o in outcomes:
        if o.kept_row is not None:
            rows.append(o.kept_row)
            continue
        title = WORKLOADS[o.name].title if o.name in WORKLOADS else o.name
        args = " ".join(a for a in o.command[2:] if not a.endswith(".md") and a != "--out")
        rows.append([f"[{o.name}](#{o.name})", title, headline(o.report), o.status,
                     f"{o.seconds:.0f} s",
                     f"`python bench/{o.name}.py {args}`".replace(" `", "`"), o.measured])
    return markdown_table(SUMMARY_HEADER, rows)


SUMMARY_HEADER = ["benchmark", "what", "result", "status", "wall time", "command", "measured"]


def _table_cells(line: str) -> list[str]:
    """The cells of one markdown table row (pipes inside backticks are not separators:
    the commands have none)."""
    return [c.strip() for c in line.strip().strip("|").split("|")]


def previous_sections(text: str) -> dict[str, tuple[list[str], str]]:
    """Parse a report written by :func:`render`: name -> (summary row, section text).
    Rows of reports older than the ``measured`` column get the report's date there."""
    stamp = re.search(r"on (\d{4}-\d{2}-\d{2} \d{2}:\d{2})", text)
    date = stamp.group(1) if stamp else ""
    rows: dict[str, list[str]] = {}
    for line in text.split("## Summary", 1)[-1].split('<a id="', 1)[0].splitlines():
        m = re.match(r"\|\s*\[(\w+)\]\(#\1\)", line)
        if m:
            cells = _table_cells(line)
            rows[m.group(1)] = cells + [date] * (len(SUMMARY_HEADER) - len(cells))
    out = {}
    parts = re.split(r'<a id="(\w+)"></a>\n', text)
    for name, body in zip(parts[1::2], parts[2::2], strict=True):
        if name in rows:
            out[name] = (rows[name], body.strip())
    return out


def render(outcomes: Sequence[Outcome], quick: bool, load: tuple[float, float]) -> str:
    """The whole RESULTS.md text."""
    from bench._common import environment

    stamp = _dt.datetime.now().strftime("%Y-%m-%d %H:%M")
    merged = any(o.kept_row is not None for o in outcomes)
    lines = [
        "# Benchmark results",
        "",
        f"Generated by `python -m bench{' --quick' if quick else ''}` on {stamp}; "
        f"{environment()}; load average {load[0]:.1f} → {load[1]:.1f}."
        + (" Sections were refreshed one at a time (`--merge`): the summary's *measured* "
           "column says when each ran." if merged else "")
        + (" **Quick settings** (smoke sizes, few repeats): ratios are indicative only."
           if quick else ""),
        "",
        "Each script runs in its own process, side by side with the installed peers on the "
        "same inputs; compile time and steady-state time are reported separately, ratios "
        "are peer time / jaxpose time unless a table says otherwise. Absolute times on a "
        "shared machine are noisy; ratios from one run are what count.",
        "",
        "## Summary",
        "",
        summary_table(outcomes),
        "",
    ]
    for o in outcomes:
        if o.kept_row is not None:
            lines += [f'<a id="{o.name}"></a>', "", o.kept_section, ""]
            continue
        lines += [f'<a id="{o.name}"></a>', "", f"## {o.name}", ""]
        if o.report:
            lines += [demote(o.report), ""]
        if o.tail:
            lines += ["Last lines of output:", "", "```", *o.tail, "```", ""]
    return "\n".join(lines).rstrip() + "\n"


def update_readme(path: Path, outcomes: Sequence[Outcome], results: Path, quick: bool) -> bool:
    """Replace the marked block in ``path`` with the summary; False if no markers."""
    text = path.read_text(encoding="utf-8")
    if README_START not in text or README_END not in text:
        return False
    rel = os.path.relpath(results, path.parent)
    block = "\n".join([
        README_START,
        f"Generated by `python -m bench{' --quick' if quick else ''}`; full tables in "
        f"[{rel}]({rel}).",
        "",
        summary_table(outcomes).replace("](#", f"]({rel}#"),
        README_END,
    ])
    head, rest = text.split(README_START, 1)
    _, tail = rest.split(README_END, 1)
    path.write_text(head + block + tail, encoding="utf-8")
    return True


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="smoke-run settings of every script")
    ap.add_argument("--only", default="", help="comma list of scripts to run")
    ap.add_argument("--skip", default="", help="comma list of scripts not to run")
    ap.add_argument("--out", default=str(HERE / "RESULTS.md"), help="report path")
    ap.add_argument("--readme", default=None, help="also update the marked block here")
    ap.add_argument("--timeout", type=float, default=3600.0, help="seconds per script")
    ap.add_argument("--merge", action="store_true",
                    help="keep the other sections of the existing --out report")
    ap.add_argument("--list", action="store_true",
                    help="list the workloads (name, title, command) and exit")
    ap.add_argument("--set", action="append", default=[], metavar="NAME=ARGS",
                    help="run NAME with ARGS (one string) instead of its registry settings; "
                    "repeatable (e.g. an accelerator run's sizes)")
    args = ap.parse_args(argv)
    names = discover()
    overrides = {}
    for item in args.set:
        name, sep, rest = item.partition("=")
        if not sep or name not in names:
            raise SystemExit(f"--set: expected NAME=ARGS with NAME one of {names}, got {item!r}")
        overrides[name] = shlex.split(rest)
    only = [n for n in args.only.split(",") if n]
    unknown = set(only) - set(names)
    if unknown:
        raise SystemExit(f"--only: no such benchmark(s) {sorted(unknown)}; present: {names}")
    names = [n for n in (only or names) if n not in set(args.skip.split(","))]
    if args.list:
        for n in names:
            title = WORKLOADS[n].title if n in WORKLOADS else "(not in the registry)"
            cmd = command(n, args.quick, Path(f"{n}.md"), overrides.get(n))[1:]
            print(f"{n:<15} {title}\n{'':15} python {os.path.relpath(cmd[0], ROOT)} "
                  + " ".join(cmd[1:]))
        return 0
    log = lambda s: print(s, file=sys.stderr, flush=True)
    load0 = os.getloadavg()[0]
    out = Path(args.out)
    kept = (previous_sections(out.read_text(encoding="utf-8"))
            if args.merge and out.is_file() else {})
    fresh: dict[str, Outcome] = {}
    outcomes: list[Outcome] = []
    order = discover() + [n for n in kept if n not in discover()]
    for n in names:
        spec = WORKLOADS.get(n)
        limit = args.timeout if args.quick or spec is None else max(args.timeout,
                                                                   60 * spec.minutes)
        o = run_one(n, args.quick, limit, log, overrides.get(n))
        o.measured = _dt.datetime.now().strftime("%Y-%m-%d %H:%M")
        log(f"    -> {o.status} in {o.seconds:.0f} s")
        if o.status != "ok" and n in kept:
            o = keep_after_failure(o, *kept[n])
        fresh[n] = o
        # written after every script, so a run stopped from outside keeps what it measured
        outcomes = [fresh[k] if k in fresh else
                    Outcome(k, [], "kept", 0.0, kept_row=kept[k][0], kept_section=kept[k][1])
                    for k in order if k in fresh or k in kept]
        out.write_text(render(outcomes, args.quick, (load0, os.getloadavg()[0])),
                       encoding="utf-8")
    log(f"wrote {out}")
    if args.readme and not update_readme(Path(args.readme), outcomes, out, args.quick):
        log(f"{args.readme}: no {README_START} / {README_END} markers; not updated")
    return 0 if all(o.status == "ok" for o in fresh.values()) else 1


if __name__ == "__main__":
    if __package__ in (None, ""):
        sys.path.insert(0, str(ROOT))
    sys.exit(main())
