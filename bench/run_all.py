"""Run every component benchmark in turn with its defaults and print their figures (``make bench``).

The end-to-end paper comparisons are separate and much longer: ``eqa bench explore`` / ``eqa bench stop``.
Each script is also runnable alone (``python bench/<name>.py --help``).
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
ORDER = ("bench_sim", "bench_mapper", "bench_planner", "bench_scorer", "bench_stopper", "bench_gateway",
         "bench_pipeline")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("names", nargs="*", default=list(ORDER), help=f"which ones (default: {' '.join(ORDER)})")
    args = parser.parse_args(argv)
    failed = []
    for name in args.names:
        script = HERE / f"{name.removesuffix('.py')}.py"
        if not script.is_file():
            parser.error(f"no benchmark {script.name}; choose from {', '.join(ORDER)}")
        sys.stdout.write(f"\n===== {script.name} =====\n")
        sys.stdout.flush()
        t0 = time.monotonic()
        rc = subprocess.call([sys.executable, str(script)])
        sys.stdout.write(f"----- {script.name}: exit {rc}, {time.monotonic() - t0:.0f} s\n")
        if rc != 0:
            failed.append(script.name)
    if failed:
        sys.stdout.write(f"failed: {', '.join(failed)}\n")
    return 1 if failed else 0


if __name__ == "__main__":
    raise SystemExit(main())
