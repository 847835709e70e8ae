"""What a fresh process's first liveliness queries see of a running fleet, as a Zenoh peer and as a client.

Starts the fleet of ``tests/fleet/test_fleet_e2e.py`` (every service, two scorer replicas) with
:class:`eqa.launcher.Fleet`, optionally ``--busy`` busy-loop processes, then ``--runs`` fresh Python processes
per mode, each connecting to the launcher's router, querying the liveliness tokens every 0.2 s until every
service is seen (or 30 s), and printing one line: seconds from ``Bus.open`` returning to the complete view, and
per query its time, the session's peer links and the services seen. The summary per mode: how many first
queries were complete, and the worst time to a complete view.

    python scripts/liveliness_probe.py [--runs 8] [--busy 4] [--modes peer,client]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from eqa.launcher import ALL_SERVICES, Fleet, free_port  # noqa: E402
from eqa.settings import Settings  # noqa: E402

PROBE = r"""
import json, sys, time
from eqa import keys
from eqa.bus import Bus
from eqa.settings import Settings
want = set(sys.argv[1:])
bus = Bus(Settings().model_copy(update={"instance": "probe"}), "probe").open()
t0 = time.monotonic()
queries = []
while time.monotonic() - t0 < 30:
    at = time.monotonic() - t0
    seen = {s for s, _ in bus.alive(keys.ALIVE_ANY, timeout=1.0)}
    queries.append([round(at, 2), len(list(bus.session.info.peers_zid())), len(seen & want)])
    if seen >= want:
        break
    time.sleep(0.2)
print(json.dumps({"complete_s": round(time.monotonic() - t0, 2), "queries": queries}))
bus.close()
"""


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--runs", type=int, default=8, help="fresh processes per mode (default 8)")
    p.add_argument("--busy", type=int, default=0, help="busy-loop processes while probing (default 0)")
    p.add_argument("--modes", default="peer,client", help="Zenoh modes of the probe, comma-separated")
    args = p.parse_args()
    modes = [m for m in args.modes.split(",") if m]
    if not modes or set(modes) - {"peer", "client"} or args.runs < 1 or args.busy < 0:
        p.error("--modes takes peer and/or client; --runs at least 1; --busy at least 0")
    with tempfile.TemporaryDirectory() as data:
        settings = Settings(data_dir=Path(data), zenoh_listen=[], zenoh_connect=[], sim_width=160, sim_height=120,
                            record=False, gateway_port=free_port())
        with Fleet(settings, services=ALL_SERVICES, scorers=2) as fleet:
            busy = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(args.busy)]
            try:
                for mode in modes:
                    env = {**os.environ, "PYTHONPATH": str(REPO), "EQA_ZENOH_CONNECT": fleet.endpoint,
                           "EQA_ZENOH_LISTEN": "", "EQA_ZENOH_MODE": mode}
                    first_complete, worst = 0, 0.0
                    for i in range(args.runs):
                        out = subprocess.run([sys.executable, "-c", PROBE, *ALL_SERVICES], capture_output=True,
                                             text=True, timeout=120, env=env, cwd=REPO)
                        if out.returncode != 0:
                            print(f"{mode} {i}: probe failed: {out.stderr.strip()[-500:]}", flush=True)
                            continue
                        row = json.loads(out.stdout.strip().splitlines()[-1])
                        first_complete += row["queries"][0][2] == len(ALL_SERVICES)
                        worst = max(worst, row["complete_s"])
                        views = " ".join(f"{t}s:{peers}p/{n}s" for t, peers, n in row["queries"][:12])
                        print(f"{mode} {i}: complete after {row['complete_s']} s; queries {views}", flush=True)
                    print(f"{mode}: first query complete in {first_complete}/{args.runs}; "
                          f"worst time to a complete view {worst} s", flush=True)
            finally:
                for b in busy:
                    b.kill()
                    b.wait()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
