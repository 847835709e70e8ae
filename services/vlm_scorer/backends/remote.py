"""OpenAI-compatible chat-completions endpoint (``scorer_backend=remote``): vLLM, SGLang, llama.cpp
server, hosted APIs.

Each query is one ``POST {remote_base_url}/chat/completions`` with the image as a PNG data URL, ``max_tokens
= 1``, ``temperature = 0``, ``logprobs = true`` and ``top_logprobs = 20``. The candidate probabilities are
read from ``choices[0].logprobs.content[0].top_logprobs``: every listed token whose text, stripped of
spaces, equals a candidate adds its probability to that candidate ("A" and " A" both count); the result is
normalised over the candidates. A candidate missing from the top list gets the probability of the least
likely listed token (an upper bound of what it could have). The four queries of a step are sent
concurrently (chat-completions has no batch call).

Timeouts are ``remote_timeout_s``; 429 and 5xx answers, timeouts and connection errors are retried up to
``remote_max_retries`` times with exponential backoff (``Retry-After`` honoured, capped). Other 4xx answers
are not retried. A response without logprobs raises :class:`BackendUnavailable` naming the settings to
change.
"""

from __future__ import annotations

import base64
import io
import logging
import math
import random
import time
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import httpx
import numpy as np
from PIL import Image

from eqa.settings import Settings
from services.vlm_scorer import prompts
from services.vlm_scorer.backends.base import BackendUnavailable, ModelBackend

log = logging.getLogger(__name__)

TOP_LOGPROBS = 20
BACKOFF_BASE_S = 0.25
BACKOFF_MAX_S = 8.0


class RemoteError(RuntimeError):
    """The endpoint failed after the retries (or refused the request)."""


def png_data_url(rgb: np.ndarray) -> str:
    buf = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(rgb)).save(buf, format="PNG", compress_level=1)
    return "data:image/png;base64," + base64.b64encode(buf.getvalue()).decode("ascii")


def read_top_logprobs(body: dict[str, Any]) -> list[tuple[str, float]]:
    """``(token, logprob)`` pairs of the first generated token; else :class:`BackendUnavailable`."""
    try:
        choice = body["choices"][0]
    except (KeyError, IndexError, TypeError) as exc:
        raise RemoteError(f"malformed chat-completions response (no choices): {str(body)[:200]}") from exc
    lp = choice.get("logprobs") if isinstance(choice, dict) else None
    content = lp.get("content") if isinstance(lp, dict) else None
    if not content:
        raise BackendUnavailable(
            "the remote endpoint returned no logprobs: point EQA_REMOTE_BASE_URL / EQA_REMOTE_MODEL at a "
            "server and model that support chat-completions logprobs with top_logprobs (vLLM, SGLang, "
            "llama.cpp server), or choose another EQA_SCORER_BACKEND"
        )
    first = content[0]
    top = first.get("top_logprobs") or [
        {"token": first.get("token", ""), "logprob": first.get("logprob", 0.0)}
    ]
    return [(str(t.get("token", "")), float(t.get("logprob", -math.inf))) for t in top]


def candidate_mass(top: list[tuple[str, float]], candidates: tuple[str, ...]) -> dict[str, float]:
    mass = dict.fromkeys(candidates, 0.0)
    finite = [lp for _, lp in top if math.isfinite(lp)]
    floor = math.exp(min(finite)) if finite else 0.0
    for token, lp in top:
        key = token.strip()
        if key in mass and math.isfinite(lp):
            mass[key] += math.exp(lp)
    return {c: (m if m > 0 else floor) for c, m in mass.items()}


def check_endpoint(base_url: str | None, model: str | None) -> None:
    """:class:`BackendUnavailable` naming the setting to set when the endpoint or the model is missing."""
    if not base_url:
        raise BackendUnavailable("scorer_backend=remote needs EQA_REMOTE_BASE_URL (e.g. http://host:8000/v1)")
    if not model:
        raise BackendUnavailable("scorer_backend=remote needs EQA_REMOTE_MODEL (the served model name)")


class RemoteBackend(ModelBackend):
    name = "remote"

    def __init__(
        self,
        base_url: str,
        model: str,
        api_key: str | None = None,
        timeout_s: float = 30.0,
        max_retries: int = 4,
    ) -> None:
        check_endpoint(base_url, model)
        self.url = base_url.rstrip("/") + "/chat/completions"
        self.model_name = model
        self.timeout_s = timeout_s
        self.max_retries = max_retries
        headers = {"Authorization": f"Bearer {api_key}"} if api_key else {}
        self.client = httpx.Client(timeout=httpx.Timeout(timeout_s), headers=headers)
        self.pool = ThreadPoolExecutor(max_workers=4, thread_name_prefix="remote-scorer")

    @classmethod
    def from_settings(cls, settings: Settings) -> RemoteBackend:
        return cls(
            settings.remote_base_url or "",
            settings.remote_model or "",
            settings.remote_api_key,
            settings.remote_timeout_s,
            settings.remote_max_retries,
        )

    def close(self) -> None:
        self.pool.shutdown(wait=False, cancel_futures=True)
        self.client.close()

    def _post(self, payload: dict[str, Any]) -> dict[str, Any]:
        last = ""
        for attempt in range(self.max_retries + 1):
            retry_after: float | None = None
            try:
                resp = self.client.post(self.url, json=payload)
            except (httpx.TimeoutException, httpx.TransportError) as exc:
                last = f"{type(exc).__name__}: {exc}"
            else:
                if resp.status_code == 200:
                    try:
                        return dict(resp.json())
                    except ValueError as exc:
                        raise RemoteError(f"{self.url} returned invalid JSON: {resp.text[:200]}") from exc
                last = f"HTTP {resp.status_code}: {resp.text[:200]}"
                if resp.status_code != 429 and resp.status_code < 500:
                    raise RemoteError(f"{self.url} refused the request: {last}")
                try:
                    retry_after = float(resp.headers.get("retry-after", ""))
                except ValueError:
                    retry_after = None
            if attempt < self.max_retries:
                delay = retry_after if retry_after is not None else BACKOFF_BASE_S * 2**attempt
                delay = min(BACKOFF_MAX_S, delay) * (1.0 + 0.1 * random.random())
                log.warning(
                    "remote scorer: %s; retry %d/%d in %.2fs", last, attempt + 1, self.max_retries, delay
                )
                time.sleep(delay)
        raise RemoteError(f"{self.url} failed after {self.max_retries + 1} attempts: {last}")

    def _messages(self, image_url: str, text: str) -> list[dict[str, Any]]:
        return [
            {"role": "system", "content": prompts.SYSTEM},
            {
                "role": "user",
                "content": [
                    {"type": "image_url", "image_url": {"url": image_url}},
                    {"type": "text", "text": text},
                ],
            },
        ]

    def _one(self, image_url: str, q: prompts.Query) -> dict[str, float]:
        body = self._post(
            {
                "model": self.model_name,
                "messages": self._messages(image_url, q.text),
                "max_tokens": 1,
                "temperature": 0.0,
                "logprobs": True,
                "top_logprobs": TOP_LOGPROBS,
            }
        )
        return candidate_mass(read_top_logprobs(body), q.candidates)

    def candidate_probs(
        self, rgb: np.ndarray, annotated: np.ndarray | None, queries: list[prompts.Query]
    ) -> list[dict[str, float]]:
        plain = png_data_url(rgb)
        marked = png_data_url(annotated) if annotated is not None else plain
        futures = [self.pool.submit(self._one, marked if q.annotated else plain, q) for q in queries]
        return [f.result() for f in futures]

    def generate(self, rgb: np.ndarray, text: str, max_new_tokens: int = 48) -> str:
        body = self._post(
            {
                "model": self.model_name,
                "messages": self._messages(png_data_url(rgb), text),
                "max_tokens": max_new_tokens,
                "temperature": 0.0,
            }
        )
        try:
            return str(body["choices"][0]["message"]["content"] or "")
        except (KeyError, IndexError, TypeError) as exc:
            raise RemoteError(f"malformed chat-completions response: {str(body)[:200]}") from exc
