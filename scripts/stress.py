"""Run the fleet's reliability tests many times while busy loops hold every core, and print how often each passed.

The tests are the sharding, takeover, fault/restart, network-namespace and end-to-end fleet ones (``--tests``
picks others: test files or node ids, comma-separated). One busy-loop process per core (``--competitors``) runs
for the whole time at normal priority, so every test sees a machine with no idle core: a test that only passes on
a quiet machine fails here. Each test file runs ``--runs`` times (each run a fresh pytest process, results read from
its JUnit report); at the end the pass counts per test, then the recovery figures of
``python -m eqa_app.benches.recovery`` (``--bench-rounds`` rounds, under the same load; ``--bench-rounds 0`` skips it).

A test that fails even once here has a bug (in the code or the test): fix it; never add a retry.

    python scripts/stress.py [--runs 30] [--tests tests/fleet/test_sharding.py,tests/fleet/test_step_resend.py]

Exit status 0 when every test passed every run (skips count as neither), 1 otherwise.
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import time
import xml.etree.ElementTree as ET
from collections import defaultdict
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
DEFAULT_TESTS = (
    "tests/fleet/test_sharding.py",
    "tests/fleet/test_takeover.py",
    "tests/fleet/test_redrive.py",
    "tests/fleet/test_sharding_fleet.py",
    "tests/fleet/test_step_resend.py",
    "tests/gateway/test_gateway_restart.py",
    "tests/mapper/test_mapper_service.py::test_killed_mapper_resumes_from_snapshot",
    "tests/fleet/test_fleet_netns.py",
    "tests/fleet/test_fleet_e2e.py",
)
BUSY = "import os\nos.nice(0)\nwhile True:\n    pass\n"


def start_competitors(n: int) -> list[subprocess.Popen[bytes]]:
    return [subprocess.Popen([sys.executable, "-c", BUSY], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                             start_new_session=True) for _ in range(n)]


def stop(procs: list[subprocess.Popen[bytes]]) -> None:
    for p in procs:
        if p.poll() is None:
            p.kill()
    for p in procs:
        p.wait(timeout=10)


def run_once(target: str, timeout: float, report: Path, basetemp: Path) -> tuple[dict[str, str], float, str]:
    """One pytest run of ``target``: ``test id -> passed/failed/skipped``, seconds, and what a failed run needs
    kept: each failure's report from the JUnit file (the assertion and its traceback), then the output's tail
    (which, behind a long captured log, no longer holds the assertion)."""
    t0 = time.monotonic()
    cmd = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", f"--junitxml={report}",
           f"--basetemp={basetemp}", target]
    try:
        proc = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, timeout=timeout)
        tail = (proc.stdout + proc.stderr)[-3000:]
    except subprocess.TimeoutExpired as exc:
        out = exc.stdout.decode(errors="replace") if isinstance(exc.stdout, bytes) else (exc.stdout or "")
        return {target: "failed"}, time.monotonic() - t0, f"timed out after {timeout:.0f} s\n{out[-3000:]}"
    outcomes: dict[str, str] = {}
    reports: list[str] = []
    if report.exists():
        for case in ET.parse(report).getroot().iter("testcase"):
            name = f"{case.get('classname', '').replace('.', '/')}.py::{case.get('name')}"
            bad = case.find("failure") if case.find("failure") is not None else case.find("error")
            if bad is not None:
                outcomes[name] = "failed"
                reports.append(f"==== {name}\n{bad.get('message', '')}\n{(bad.text or '')[-20000:]}\n")
            elif case.find("skipped") is not None:
                outcomes[name] = "skipped"
            else:
                outcomes[name] = "passed"
        report.unlink()
    if not outcomes:
        outcomes[target] = "failed"  # nothing ran: collection error
    return outcomes, time.monotonic() - t0, "".join(reports) + tail


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--runs", type=int, default=30, help="runs of each test file (default 30)")
    p.add_argument("--tests", default=",".join(DEFAULT_TESTS),
                   help="comma-separated test files or node ids (default: the reliability tests, see above)")
    p.add_argument("--competitors", type=int, default=os.cpu_count() or 1,
                   help=f"busy-loop processes (default one per core: {os.cpu_count()})")
    p.add_argument("--timeout", type=float, default=900.0, help="seconds for one pytest run (default 900)")
    p.add_argument("--bench-rounds", type=int, default=3,
                   help="rounds of eqa_app.benches.recovery at the end (default 3; 0 = skip)")
    p.add_argument("--failures", type=Path, default=None,
                   help="directory for the output of every failed run (default: a temporary one, printed)")
    args = p.parse_args(argv)
    tests = [t for t in args.tests.split(",") if t]
    if not (1 <= args.runs <= 10_000 and 0 <= args.competitors <= 256 and 0 <= args.bench_rounds <= 50 and tests):
        p.error("1 <= runs <= 10000, 0 <= competitors <= 256, 0 <= bench-rounds <= 50, at least one test")
    for t in tests:
        if not (REPO / t.split("::")[0]).is_file():
            p.error(f"no test file {t.split('::')[0]} (paths are relative to {REPO})")
    failures = args.failures or Path(tempfile.mkdtemp(prefix="eqa-stress-"))
    failures.mkdir(parents=True, exist_ok=True)
    counts: dict[str, dict[str, int]] = defaultdict(lambda: defaultdict(int))
    load0 = os.getloadavg()
    t_start = time.monotonic()
    competitors = start_competitors(args.competitors)
    print(f"stress: {len(tests)} target(s) x {args.runs} run(s), {args.competitors} busy loop(s) on "
          f"{os.cpu_count()} core(s); load average {load0[0]:.1f} before", flush=True)
    try:
        total = len(tests) * args.runs
        done = 0
        for run in range(args.runs):
            for target in tests:
                report = failures / f"report-{os.getpid()}.xml"
                stem = f"{Path(target.split('::')[0]).stem}-run{run + 1}"
                # the run's temporary directories hold the fleet's service logs: kept when it fails
                basetemp = failures / f"{stem}-tmp"
                outcomes, secs, tail = run_once(target, args.timeout, report, basetemp)
                done += 1
                bad = [n for n, o in outcomes.items() if o == "failed"]
                for name, outcome in outcomes.items():
                    counts[name][outcome] += 1
                where = ""
                if bad:
                    log = failures / f"{stem}.txt"
                    log.write_text(tail)
                    where = f"; output: {log}, its temporary files (service logs): {basetemp}"
                else:
                    shutil.rmtree(basetemp, ignore_errors=True)
                print(f"[{done}/{total}] run {run + 1} {target}: {len(outcomes) - len(bad)} ok, {len(bad)} failed "
                      f"({secs:.0f} s){where}", flush=True)
        bench_lines: list[str] = []
        if args.bench_rounds:
            print(f"eqa_app.benches.recovery --rounds {args.bench_rounds} under the same load ...", flush=True)
            proc = subprocess.run([sys.executable, "-m", "eqa_app.benches.recovery", "--rounds",
                                   str(args.bench_rounds)], cwd=REPO, capture_output=True, text=True,
                                  timeout=args.timeout * 2)
            out = proc.stdout.splitlines()
            head = next((i for i, line in enumerate(out) if line.startswith("case ")), len(out))
            bench_lines = out[head:] or (proc.stdout + proc.stderr).splitlines()[-10:]
    finally:
        stop(competitors)
    load1 = os.getloadavg()
    print(f"\npass counts ({args.runs} run(s) each, {args.competitors} busy loop(s) on {os.cpu_count()} core(s), "
          f"{(time.monotonic() - t_start) / 60:.0f} min; load average {load0[0]:.1f} before, {load1[0]:.1f} after)")
    ok = True
    for name in sorted(counts):
        c = counts[name]
        runs = c["passed"] + c["failed"]
        mark = "" if not c["failed"] else "   <-- FLAKY" if c["passed"] else "   <-- FAILS"
        ok = ok and not c["failed"]
        skipped = f" (skipped {c['skipped']})" if c["skipped"] else ""
        print(f"{c['passed']:>5}/{runs:<5} {name}{skipped}{mark}")
    if bench_lines:
        print("\nrecovery (eqa_app/benches/recovery.py, same load):")
        print("\n".join(bench_lines))
    if not ok:
        print(f"\nfailed runs' output: {failures}")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
