"""``eqa scorer ...`` commands.

eqa scorer build-tiny PATH     write a tiny random Qwen2-VL directory (offline) to try scorer_backend=hf
eqa scorer replicas            list the live scorer replicas
eqa scorer ping [--n N]        score N synthetic frames through the replica pool and print the results
eqa scorer check --url URL [--model M]
                               probe an OpenAI-compatible endpoint (models, image input, logprobs, latency of
                               one scoring step) and print the mode the remote scorer will use and what to set
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from eqa.bus import Bus
    from eqa.scorer_client import ScorerClient


def _fail(msg: str) -> int:
    print(f"error: {msg}", file=sys.stderr)
    return 2


def cmd_build_tiny(args: argparse.Namespace) -> int:
    from services.vlm_scorer.tiny import build_tiny_qwen2vl

    path = Path(args.path)
    if path.exists() and any(path.iterdir()) and not args.force:
        return _fail(f"{path} exists and is not empty (use --force to overwrite)")
    out = build_tiny_qwen2vl(path)
    print(f"tiny random Qwen2-VL written to {out}; use EQA_SCORER_BACKEND=hf EQA_HF_MODEL_PATH={out}")
    return 0


def _client(timeout: float) -> tuple[Bus, ScorerClient]:
    from eqa.bus import Bus
    from eqa.scorer_client import ScorerClient
    from eqa.settings import Settings

    settings = Settings()
    bus = Bus(settings, "gateway", f"cli-{settings.instance}"[:64]).open()
    client = ScorerClient(bus, settings, timeout_s=timeout)
    client.wait_for_replicas(1, timeout=min(timeout, 3.0))
    return bus, client


def cmd_replicas(args: argparse.Namespace) -> int:
    bus, client = _client(args.timeout)
    try:
        for r in client.replicas():
            print(r)
        return 0 if client.replicas() else 1
    finally:
        bus.close()


def cmd_ping(args: argparse.Namespace) -> int:
    import numpy as np

    from eqa.messages import PromptPoint, Question, ScoreRequest
    from eqa.scorer_client import ScorerError, ScorerUnavailable

    if args.n < 1:
        return _fail("--n must be >= 1")
    bus, client = _client(args.timeout)
    try:
        rng = np.random.default_rng(0)
        q = Question(
            text="What color is the sofa?",
            choices=["Red", "Blue", "Green", "White"],
            scene="ping",
            query={"type": "identification", "category": "sofa"},
        )
        for i in range(args.n):
            req = ScoreRequest(
                episode_id="ping",
                step=i,
                question=q,
                rgb=(rng.random((120, 160, 3)) * 255).astype(np.uint8),
                prompt_points=[
                    PromptPoint(label="A", x=0, y=0, u=40, v=90),
                    PromptPoint(label="B", x=0, y=0, u=120, v=90),
                ],
            )
            try:
                res = client.score(req)
            except (ScorerError, ScorerUnavailable) as exc:
                print(f"error: {exc}", file=sys.stderr)
                return 1
            print(
                json.dumps(
                    {
                        "replica": res.replica,
                        "backend": res.backend,
                        "model": res.model,
                        "answer_probs": [round(p, 4) for p in res.answer_probs],
                        "relevance": round(res.relevance, 4),
                        "lsv": [round(v, 4) for v in res.lsv],
                        "gsv": round(res.gsv, 4),
                        "latency_ms": round(res.latency_ms, 2),
                    }
                )
            )
        return 0
    finally:
        bus.close()


def cmd_check(args: argparse.Namespace) -> int:
    from eqa.settings import Settings
    from services.vlm_scorer.backends.remote import probe_endpoint

    settings = Settings()
    url = args.url or settings.remote_base_url
    if not url:
        return _fail("give --url (e.g. http://127.0.0.1:8000/v1) or set EQA_REMOTE_BASE_URL")
    if not url.startswith(("http://", "https://")):
        return _fail(f"--url {url!r} must start with http:// or https://")
    samples = args.samples if args.samples is not None else settings.remote_samples
    if not 1 <= samples <= 64:
        return _fail("--samples must be 1..64")
    report = probe_endpoint(
        url,
        args.model or settings.remote_model,
        api_key=settings.remote_api_key,
        timeout_s=args.timeout,
        mode=args.mode or settings.remote_mode,
        samples=samples,
        temperature=settings.remote_sample_temperature,
        score_step=not args.no_step,
    )
    for line in report.lines():
        print(line)
    return 0 if report.usable else 1


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("scorer", help="VLM scorer tools (tiny model, replicas, ping, endpoint check)")
    sub = p.add_subparsers(dest="scorer_cmd", required=True)
    b = sub.add_parser("build-tiny", help="write a tiny random Qwen2-VL model directory (offline)")
    b.add_argument("path")
    b.add_argument("--force", action="store_true")
    b.set_defaults(func=cmd_build_tiny)
    r = sub.add_parser("replicas", help="list live scorer replicas")
    r.add_argument("--timeout", type=float, default=3.0)
    r.set_defaults(func=cmd_replicas)
    g = sub.add_parser("ping", help="score synthetic frames through the replica pool")
    g.add_argument("--n", type=int, default=1)
    g.add_argument("--timeout", type=float, default=10.0)
    g.set_defaults(func=cmd_ping)
    c = sub.add_parser(
        "check",
        help="probe an OpenAI-compatible endpoint and say which scorer mode to use",
        description="Probe an OpenAI-compatible chat-completions endpoint: models listed (GET /models), image "
        "input accepted, logprobs returned, the latency and HTTP calls of one scoring step; print the mode the "
        "remote scorer will use (logprobs, or sampling for servers without logprobs) and the EQA_* settings. "
        "Exit 0 when usable, 1 when not.",
    )
    c.add_argument("--url", default=None, help="base URL ending in /v1 (default EQA_REMOTE_BASE_URL)")
    c.add_argument("--model", default=None, help="served model name (default EQA_REMOTE_MODEL, else the first "
                   "listed)")
    c.add_argument("--mode", choices=("auto", "logprobs", "sampling"), default=None,
                   help="force a mode (default EQA_REMOTE_MODE=auto: logprobs when returned, else sampling)")
    c.add_argument("--samples", type=int, default=None, help="samples per query in sampling mode (default "
                   "EQA_REMOTE_SAMPLES=8)")
    c.add_argument("--timeout", type=float, default=60.0, help="seconds per HTTP request")
    c.add_argument("--no-step", action="store_true", help="skip the timed scoring step")
    c.set_defaults(func=cmd_check)
