"""How much `make test`'s first-time set-up downloads: the wheels pip resolves for the project's .venv (as
scripts/setup.sh installs it: torch 2.13.0, then ``-e .[dev]``), each sized from its file (a configured local
directory) or by an HTTP HEAD of its URL; written to bench/results/setup-download/sizes.json.

    .venv/bin/python -m eqa_app.benches.setup_download_size [--isolated-torch]

``--isolated-torch`` also sizes what ``pip install torch==2.13.0`` takes from PyPI alone (no configured indexes:
the CUDA build and its nvidia wheels). Nothing is installed (``pip install --dry-run``). The llama.cpp sdist
(scripts/setup-llama.sh) and the Debian packages (scripts/setup.sh) are not wheels: they are added by hand in
docs/model-servers-llamacpp.md.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import urllib.parse
import urllib.request
from pathlib import Path

from eqa_app.benches import harness

REPO = harness.REPO
OUT = REPO / "bench" / "results" / "setup-download" / "sizes.json"


def resolve(args: list[str]) -> list[dict]:
    with tempfile.TemporaryDirectory() as tmp:
        report = Path(tmp) / "report.json"
        subprocess.run([sys.executable, "-m", "pip", "install", "--dry-run", "--ignore-installed", "--quiet",
                        "--report", str(report), *args], cwd=REPO, check=True, stderr=subprocess.DEVNULL)
        return json.loads(report.read_text())["install"]


def size(url: str) -> int:
    if url.startswith("file://"):
        return Path(urllib.parse.unquote(url[len("file://"):])).stat().st_size
    with urllib.request.urlopen(urllib.request.Request(url, method="HEAD"), timeout=60) as resp:
        return int(resp.headers["Content-Length"])


def table(items: list[dict]) -> list[dict]:
    rows = [{"name": it["metadata"]["name"], "version": it["metadata"]["version"],
             "bytes": size(it["download_info"]["url"]),
             "source": "local" if it["download_info"]["url"].startswith("file://") else "remote"} for it in items]
    return sorted(rows, key=lambda r: -r["bytes"])


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--isolated-torch", action="store_true")
    a = ap.parse_args(argv)
    out: dict = {"command": "pip install --dry-run --ignore-installed --report - torch==2.13.0 -e .[dev]"}
    # with the configured indexes (here a local directory holds torch 2.13.0+cpu; elsewhere add PyTorch's CPU
    # index as scripts/setup.sh does, for torch alone: an extra index is asked for every package resolved)
    out["venv"] = table(resolve(["torch==2.13.0", "-e", ".[dev]"]))
    out["venv_total_bytes"] = sum(r["bytes"] for r in out["venv"])
    print(f"venv: {len(out['venv'])} wheels, {out['venv_total_bytes'] / 1e6:.0f} MB")
    for r in out["venv"][:8]:
        print(f"  {r['bytes'] / 1e6:7.1f} MB  {r['name']} {r['version']} ({r['source']})")
    if a.isolated_torch:
        out["pypi_torch"] = table(resolve(["--isolated", "torch==2.13.0"]))
        out["pypi_torch_total_bytes"] = sum(r["bytes"] for r in out["pypi_torch"])
        print(f"torch==2.13.0 from PyPI alone: {out['pypi_torch_total_bytes'] / 1e6:.0f} MB")
    OUT.parent.mkdir(parents=True, exist_ok=True)
    OUT.write_text(json.dumps(out, indent=1) + "\n")
    print(f"written to {OUT.relative_to(REPO)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
