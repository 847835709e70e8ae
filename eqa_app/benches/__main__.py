"""Run the component benchmarks in turn with their defaults and print their figures (``make bench``).

The end-to-end paper comparisons are separate and much longer: ``eqa bench explore`` / ``eqa bench stop``.
Each benchmark is also runnable alone: ``python -m eqa_app.benches.<name> --help``.
"""

from __future__ import annotations

import subprocess
import sys
import time

from eqa_app.benches.harness import catalogue, command, environment, names, parser

DEFAULT = ("sim", "mapper", "planner", "scorer", "stopper", "gateway", "pipeline")


def main(argv: list[str] | None = None) -> int:
    ap = parser(f"{__doc__}\nbenchmarks:\n{catalogue()}")
    ap.add_argument("names", nargs="*", default=list(DEFAULT), help=f"which ones (default: {' '.join(DEFAULT)})")
    args = ap.parse_args(argv)
    unknown = [n for n in args.names if n not in names()]
    if unknown:
        ap.error(f"no benchmark {', '.join(unknown)}; choose from {', '.join(names())}")
    failed = []
    for name in args.names:
        sys.stdout.write(f"\n===== {name} =====\n")
        sys.stdout.flush()
        t0 = time.monotonic()
        rc = subprocess.call(command(name), env=environment())
        sys.stdout.write(f"----- {name}: exit {rc}, {time.monotonic() - t0:.0f} s\n")
        if rc != 0:
            failed.append(name)
    if failed:
        sys.stdout.write(f"failed: {', '.join(failed)}\n")
    return 1 if failed else 0


if __name__ == "__main__":
    raise SystemExit(main())
