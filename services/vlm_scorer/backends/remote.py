"""OpenAI-compatible chat-completions endpoint (``scorer_backend=remote``): vLLM, SGLang, llama.cpp
server, hosted APIs.

Each query is one ``POST {remote_base_url}/chat/completions`` with the image as a PNG data URL, ``max_tokens
= 1``, ``temperature = 0``, ``logprobs = true`` and ``top_logprobs = 20``. The candidate probabilities are
read from ``choices[0].logprobs.content[0].top_logprobs``: every listed token whose text, stripped of
spaces, equals a candidate adds its probability to that candidate ("A" and " A" both count); the result is
normalised over the candidates. A candidate missing from the top list gets the probability of the least
likely listed token (an upper bound of what it could have). The four queries of a step are sent
concurrently (chat-completions has no batch call), and so are those of the steps of a replica's batch
(:meth:`RemoteBackend.score_many`), on connections kept alive between steps (one ``httpx.Client``).

Timeouts are ``remote_timeout_s``; 429 and 5xx answers, timeouts and connection errors are retried up to
``remote_max_retries`` times with exponential backoff (``Retry-After`` honoured, capped). Other 4xx answers
are not retried.

Modes (``EQA_REMOTE_MODE``):

- ``logprobs``: as above. A response without logprobs raises :class:`BackendUnavailable` naming the settings.
- ``sampling`` for endpoints that return no logprobs (``transformers serve``, many hosted APIs): each query
  asks for ``remote_samples`` = k completions at ``remote_sample_temperature`` (``max_tokens`` =
  :data:`SAMPLE_MAX_TOKENS`); the first word of each completion that equals a candidate is one vote and the
  candidate's probability is its vote frequency, the plug-in estimate of the model's next-token
  distribution restricted to the candidates (the same distribution the logprobs mode reads, Explore-EQA's
  "normalized probability"). Completions that name no candidate are dropped; a query with none left
  gives the uniform distribution. Each probability is a multiple of 1/valid samples: that resolution is
  carried in the scores (:attr:`Scores.resolution`, ``ScoreResult.resolution``), and its standard error is
  at most 0.5/sqrt(k). Cost per step: 4 queries x 1 call when the server honours ``n`` (asked once with
  ``n = k``; a server that answers fewer choices or refuses ``n`` is asked k times with ``n = 1`` from
  then on), else 4 x k calls; the time grows with k in both cases (k completions are generated).
- ``auto`` (default): logprobs until the first response comes back without them, then sampling for the
  rest of the replica's life (logged once; the scores say which mode made them, and the stopper warns
  when its calibration table was made in the other mode).

:func:`probe_endpoint` is ``eqa scorer check``: models listed, image input accepted, logprobs returned,
the latency of one scoring step, and the mode and settings to use.
"""

from __future__ import annotations

import base64
import io
import logging
import math
import random
import re
import threading
import time
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any, Literal

import httpx
import numpy as np
from PIL import Image

from eqa.messages import ScoreRequest
from eqa.settings import SettingsGroup
from services.vlm_scorer import prompts
from services.vlm_scorer.backends.base import BackendUnavailable, ModelBackend, ProbeItem, Scores

log = logging.getLogger(__name__)

TOP_LOGPROBS = 20
BACKOFF_BASE_S = 0.25
BACKOFF_MAX_S = 8.0
SAMPLE_MAX_TOKENS = 3  # enough for "Yes", " B." etc.; only the first word counts
MAX_SAMPLES = 64
QUERIES_PER_STEP = 4  # answer, relevance, LSV, GSV (prompts.step_queries)
# steps of a replica's batch whose queries are in flight at once (score_many); their connections are kept alive
STEPS_IN_FLIGHT = 8

Mode = Literal["auto", "logprobs", "sampling"]
_FIRST_WORD = re.compile(r"[A-Za-z]+")


class RemoteError(RuntimeError):
    """The endpoint failed after the retries (or refused the request)."""


class NoLogprobs(BackendUnavailable):
    """The endpoint answered without logprobs (logprobs mode cannot work; sampling mode can)."""


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
        raise NoLogprobs(
            "the remote endpoint returned no logprobs: set EQA_REMOTE_MODE=sampling (or auto) to estimate the "
            "answer distribution from sampled completions, or point EQA_REMOTE_BASE_URL / EQA_REMOTE_MODEL at "
            "a server and model that support chat-completions logprobs with top_logprobs (vLLM, SGLang, "
            "llama.cpp server), or choose another EQA_SCORER_BACKEND (check with `eqa scorer check`)"
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


def first_word(text: str) -> str:
    """The first run of letters of a completion ("" if none): " B." -> "B", "Yes, it is" -> "Yes"."""
    m = _FIRST_WORD.search(text or "")
    return m.group(0) if m else ""


def sample_votes(texts: list[str], candidates: tuple[str, ...]) -> tuple[dict[str, float], int]:
    """Vote counts of ``candidates`` among the completions and the number of valid ones (a completion whose
    first word is a candidate, compared exactly, else case-insensitively)."""
    votes = dict.fromkeys(candidates, 0.0)
    lower = {c.lower(): c for c in candidates}
    valid = 0
    for t in texts:
        w = first_word(t)
        key = w if w in votes else lower.get(w.lower())
        if key is not None:
            votes[key] += 1.0
            valid += 1
    return votes, valid


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
        mode: Mode = "logprobs",
        samples: int = 8,
        temperature: float = 1.0,
    ) -> None:
        check_endpoint(base_url, model)
        if mode not in ("auto", "logprobs", "sampling"):
            raise BackendUnavailable(f"EQA_REMOTE_MODE={mode!r}: use auto, logprobs or sampling")
        if not 1 <= samples <= MAX_SAMPLES:
            raise BackendUnavailable(f"EQA_REMOTE_SAMPLES={samples}: use 1..{MAX_SAMPLES}")
        self.base_url = base_url.rstrip("/")
        self.url = self.base_url + "/chat/completions"
        self.model_name = model
        self.timeout_s = timeout_s
        self.max_retries = max_retries
        self.mode_setting: Mode = mode
        self.mode = "sampling" if mode == "sampling" else "logprobs"
        self.samples = samples
        self.temperature = temperature
        self.n_supported: bool | None = None  # does the server honour ``n``? (sampling; learnt on first use)
        self.calls = 0  # HTTP requests sent (retries included): the cost counter ``eqa scorer check`` reports
        self._lock = threading.Lock()
        self._step_resolution = 0.0
        headers = {"Authorization": f"Bearer {api_key}"} if api_key else {}
        in_flight = QUERIES_PER_STEP * STEPS_IN_FLIGHT
        self.client = httpx.Client(timeout=httpx.Timeout(timeout_s), headers=headers,
                                   limits=httpx.Limits(max_connections=in_flight, max_keepalive_connections=in_flight))
        self.pool = ThreadPoolExecutor(max_workers=in_flight, thread_name_prefix="remote-scorer")

    @classmethod
    def from_settings(cls, settings: SettingsGroup) -> RemoteBackend:
        return cls(
            settings.remote_base_url or "",
            settings.remote_model or "",
            settings.remote_api_key,
            settings.remote_timeout_s,
            settings.remote_max_retries,
            mode=settings.remote_mode,
            samples=settings.remote_samples,
            temperature=settings.remote_sample_temperature,
        )

    def close(self) -> None:
        self.pool.shutdown(wait=False, cancel_futures=True)
        self.client.close()

    def _post(self, payload: dict[str, Any]) -> dict[str, Any]:
        last = ""
        for attempt in range(self.max_retries + 1):
            retry_after: float | None = None
            with self._lock:
                self.calls += 1
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

    @property
    def resolution(self) -> float:
        """Nominal resolution of a probability: 0 (exact) with logprobs, 1/k when sampling k completions."""
        return 0.0 if self.mode == "logprobs" else 1.0 / self.samples

    def calls_per_step(self) -> int:
        """HTTP calls of one scoring step without retries (a question without choices adds one)."""
        if self.mode == "logprobs" or self.n_supported is not False:
            return QUERIES_PER_STEP
        return QUERIES_PER_STEP * self.samples

    def _logprobs(self, image_url: str, q: prompts.Query) -> dict[str, float]:
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

    def sample_texts(self, image_url: str, text: str, k: int) -> list[str]:
        """``k`` sampled completions of one prompt: one call with ``n = k`` where the server honours ``n``,
        else k calls (at most k + 1 calls in all)."""
        texts: list[str] = []
        calls = 0
        while len(texts) < k and calls <= k:
            want = k - len(texts)
            ask = want if self.n_supported is not False else 1
            payload: dict[str, Any] = {
                "model": self.model_name,
                "messages": self._messages(image_url, text),
                "max_tokens": SAMPLE_MAX_TOKENS,
                "temperature": self.temperature,
            }
            if ask > 1:
                payload["n"] = ask
            calls += 1
            try:
                body = self._post(payload)
            except RemoteError as exc:
                if ask > 1 and self.n_supported is not True and "refused the request" in str(exc):
                    log.warning("remote scorer: %s refused n=%d (%s); sampling by repeated calls", self.url,
                                ask, exc)
                    self.n_supported = False
                    continue
                raise
            choices = body.get("choices")
            if not isinstance(choices, list) or not choices:
                raise RemoteError(f"malformed chat-completions response (no choices): {str(body)[:200]}")
            got = []
            for c in choices:
                msg = c.get("message") if isinstance(c, dict) else None
                got.append(str((msg or {}).get("content") or ""))
            if ask > 1 and self.n_supported is None:
                self.n_supported = len(got) >= ask
                if not self.n_supported:
                    log.warning("remote scorer: %s answered %d choice(s) for n=%d; sampling by repeated calls "
                                "(%d calls per step)", self.url, len(got), ask, QUERIES_PER_STEP * k)
            texts.extend(got[:want])
        return texts

    def _sampled(self, image_url: str, q: prompts.Query) -> tuple[dict[str, float], int]:
        votes, valid = sample_votes(self.sample_texts(image_url, q.text, self.samples), q.candidates)
        if valid == 0:
            log.warning("remote scorer: none of %d samples named a candidate of the %s query; uniform",
                        self.samples, q.name)
        return votes, valid

    def _one(self, image_url: str, q: prompts.Query) -> dict[str, float]:
        return self._query(image_url, q)[0]

    def _query(self, image_url: str, q: prompts.Query) -> tuple[dict[str, float], float]:
        """Candidate masses of one query and their resolution (0 exact, 1/valid samples, 1 = no information)."""
        if self.mode == "logprobs":
            try:
                return self._logprobs(image_url, q), 0.0
            except NoLogprobs:
                if self.mode_setting != "auto":
                    raise
                with self._lock:
                    if self.mode == "logprobs":
                        self.mode = "sampling"
                        log.warning(
                            "remote scorer: %s returns no logprobs; EQA_REMOTE_MODE=auto switches to sampling "
                            "with %d samples per query (resolution %.3g); set EQA_REMOTE_MODE=sampling to "
                            "say so", self.url, self.samples, 1.0 / self.samples)
        votes, valid = self._sampled(image_url, q)
        return votes, (1.0 / valid if valid else 1.0)

    def candidate_probs(
        self, rgb: np.ndarray, annotated: np.ndarray | None, queries: list[prompts.Query]
    ) -> list[dict[str, float]]:
        plain = png_data_url(rgb)
        marked = png_data_url(annotated) if annotated is not None else plain
        futures = [self.pool.submit(self._query, marked if q.annotated else plain, q) for q in queries]
        out = [f.result() for f in futures]
        self._step_resolution = max((r for _, r in out), default=0.0)
        return [m for m, _ in out]

    def score_many(self, reqs: list[ScoreRequest]) -> list[Scores | Exception]:
        """Several steps of a replica's batch: the queries of all of them in flight together (up to
        :data:`STEPS_IN_FLIGHT` steps' worth; chat-completions has no batch call, and a server that batches
        requests itself, like vLLM, serves concurrent ones together). Per request its :class:`Scores` with its
        own mode and resolution, or the exception preparing or scoring it raised."""
        out: list[Scores | Exception] = []
        ready: list[tuple[int, ProbeItem, list[str], list[Future[tuple[dict[str, float], float]]]]] = []
        for i, req in enumerate(reqs):
            try:
                item, proposed = self.prepare(req)
                plain = png_data_url(item.rgb)
                marked = png_data_url(item.annotated) if item.annotated is not None else plain
            except Exception as exc:
                out.append(exc)
                continue
            out.append(RuntimeError("not scored"))
            ready.append((i, item, proposed, [self.pool.submit(self._query, marked if q.annotated else plain, q)
                                              for q in item.queries]))
        for i, item, proposed, futures in ready:
            try:
                got = [f.result() for f in futures]
            except Exception as exc:
                out[i] = exc
                continue
            scores = self.finish(reqs[i], item, proposed, [m for m, _ in got])
            scores.mode = self.mode
            scores.resolution = max((r for _, r in got), default=0.0)
            out[i] = scores
        return out

    def score(self, req: Any) -> Scores:
        """:meth:`ModelBackend.score`, with the mode and the step's resolution (one request at a time)."""
        self._step_resolution = 0.0
        scores = super().score(req)
        scores.mode = self.mode
        scores.resolution = self._step_resolution
        return scores

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


# ---- eqa scorer check / eqa up: probe an endpoint -------------------------------------------------------
PROBE_TEXT = "Is there anything in this image? Answer Yes or No."


@dataclass
class ProbeReport:
    """What ``eqa scorer check`` found out about an endpoint, and the mode the scorer will use."""

    base_url: str
    model: str = ""
    models: list[str] | None = None  # None: the server has no usable GET /models
    image_ok: bool = False
    logprobs: bool = False
    mode: str = ""  # "logprobs" / "sampling" / "" (unusable)
    n_supported: bool | None = None
    samples: int = 0
    calls_per_step: int = 0
    step_latency_s: float | None = None
    problems: list[str] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)

    @property
    def usable(self) -> bool:
        return not self.problems and bool(self.mode)

    def settings_lines(self) -> list[str]:
        """The ``EQA_*`` settings for a fleet on this endpoint."""
        lines = ["EQA_SCORER_BACKEND=remote", f"EQA_REMOTE_BASE_URL={self.base_url}", f"EQA_REMOTE_MODEL={self.model}",
                 f"EQA_REMOTE_MODE={self.mode}"]
        if self.mode == "sampling":
            lines.append(f"EQA_REMOTE_SAMPLES={self.samples}")
        return lines

    def lines(self) -> list[str]:
        """Human-readable report, one finding per line."""
        out = [f"endpoint: {self.base_url}"]
        if self.models is None:
            out.append("models listed: no (GET /models failed; the model name must be given)")
        else:
            out.append(f"models listed: {', '.join(self.models) or '(none)'}")
        out.append(f"model: {self.model or '(none)'}")
        out.append(f"image input accepted: {'yes' if self.image_ok else 'no'}")
        out.append(f"logprobs returned: {'yes' if self.logprobs else 'no'}")
        if self.mode == "sampling":
            n = {True: "yes (one call per query)", False: "no (repeated calls)", None: "not tried"}
            out.append(f"n per request honoured: {n[self.n_supported]}")
        if self.step_latency_s is not None:
            out.append(f"one scoring step: {self.step_latency_s * 1000:.0f} ms, {self.calls_per_step} HTTP calls")
        out.extend(f"note: {n}" for n in self.notes)
        out.extend(f"problem: {p}" for p in self.problems)
        if self.usable:
            res = "exact probabilities" if self.mode == "logprobs" else f"resolution 1/{self.samples} per query"
            out.append(f"mode: {self.mode} ({res})")
            out.append("set: " + " ".join(self.settings_lines()))
        else:
            out.append("mode: none - the scorer cannot use this endpoint (see the problems above)")
        return out


def _probe_image() -> np.ndarray:
    rng = np.random.default_rng(0)
    return (rng.random((64, 64, 3)) * 255).astype(np.uint8)


def _probe_models(client: httpx.Client, rep: ProbeReport, model: str | None) -> bool:
    """``GET /models`` and the model to probe (``model``, else the first listed) into ``rep``; False when the
    probe cannot go on (the server is not reachable, or no model is known)."""
    try:
        resp = client.get(rep.base_url + "/models")
        if resp.status_code == 200:
            data = resp.json().get("data", [])
            rep.models = [str(m.get("id")) for m in data if isinstance(m, dict) and m.get("id")]
        else:
            rep.notes.append(f"GET /models answered HTTP {resp.status_code}")
    except (httpx.TransportError, httpx.TimeoutException) as exc:
        rep.problems.append(f"cannot reach {rep.base_url}: {type(exc).__name__}: {exc} (is the server up? "
                            f"the URL ends in /v1 for most servers)")
        return False
    except (ValueError, AttributeError) as exc:
        rep.notes.append(f"GET /models returned no model list ({exc})")
    if model:
        rep.model = model
        if rep.models is not None and model not in rep.models:
            rep.notes.append(f"{model!r} is not among the listed models; the server may still accept it")
    elif rep.models:
        rep.model = rep.models[0]
        if len(rep.models) > 1:
            rep.notes.append(f"no --model given: using the first listed, {rep.model!r}")
    else:
        rep.problems.append("no model listed by the server: give --model (EQA_REMOTE_MODEL)")
        return False
    return True


def _probe_image_chat(client: httpx.Client, rep: ProbeReport) -> bool:
    """One image + Yes/No chat completion asking for logprobs: whether the model takes an image and returns
    logprobs, into ``rep``; False when the probe cannot go on."""
    payload = {
        "model": rep.model,
        "messages": [{"role": "user", "content": [
            {"type": "image_url", "image_url": {"url": png_data_url(_probe_image())}},
            {"type": "text", "text": PROBE_TEXT}]}],
        "max_tokens": 1,
        "temperature": 0.0,
        "logprobs": True,
        "top_logprobs": 5,
    }
    try:
        resp = client.post(rep.base_url + "/chat/completions", json=payload)
    except (httpx.TransportError, httpx.TimeoutException) as exc:
        rep.problems.append(f"chat completion with an image failed: {type(exc).__name__}: {exc}")
        return False
    if resp.status_code != 200:
        rep.problems.append(f"chat completion with an image refused: HTTP {resp.status_code}: "
                            f"{resp.text[:200]} (is {rep.model!r} a vision-language model?)")
        return False
    rep.image_ok = True
    try:
        read_top_logprobs(resp.json())
        rep.logprobs = True
    except NoLogprobs:
        rep.logprobs = False
    except (RemoteError, ValueError) as exc:
        rep.problems.append(f"malformed chat-completions response: {exc}")
        return False
    return True


def _probe_step(rep: ProbeReport, api_key: str | None, timeout_s: float, samples: int, temperature: float) -> None:
    """One full scoring step of a synthetic frame in ``rep.mode`` through :class:`RemoteBackend`, timed, with
    the HTTP calls it took, into ``rep``."""
    from eqa.messages import PromptPoint, Question, ScoreRequest

    backend = RemoteBackend(rep.base_url, rep.model, api_key, timeout_s, max_retries=1,
                            mode=rep.mode, samples=samples, temperature=temperature)  # type: ignore[arg-type]
    rgb = np.ascontiguousarray(np.tile(_probe_image(), (2, 2, 1))[:96, :128])
    req = ScoreRequest(
        episode_id="check", step=0, rgb=rgb,
        question=Question(text="What color is the sofa?", choices=["Red", "Blue", "Green", "White"], scene="check"),
        prompt_points=[PromptPoint(label="A", x=0, y=0, u=32, v=70), PromptPoint(label="B", x=0, y=0, u=96, v=70)],
    )
    try:
        t0 = time.perf_counter()
        backend.score(req)
        rep.step_latency_s = time.perf_counter() - t0
        rep.calls_per_step = backend.calls
        rep.n_supported = backend.n_supported if rep.mode == "sampling" else None
    except (RemoteError, BackendUnavailable) as exc:
        rep.problems.append(f"one scoring step in {rep.mode} mode failed: {exc}")
    finally:
        backend.close()


def probe_endpoint(
    base_url: str,
    model: str | None = None,
    api_key: str | None = None,
    timeout_s: float = 30.0,
    mode: Mode = "auto",
    samples: int = 8,
    temperature: float = 1.0,
    score_step: bool = True,
) -> ProbeReport:
    """Probe an OpenAI-compatible endpoint: ``GET /models``, one image + Yes/No chat completion asking for
    logprobs, then (``score_step``) one full scoring step of a synthetic frame in the chosen mode, timed.
    Never raises for what the endpoint does: findings go to :attr:`ProbeReport.problems`."""
    rep = ProbeReport(base_url=base_url.rstrip("/"), samples=samples)
    headers = {"Authorization": f"Bearer {api_key}"} if api_key else {}
    with httpx.Client(timeout=httpx.Timeout(timeout_s), headers=headers) as client:
        if not (_probe_models(client, rep, model) and _probe_image_chat(client, rep)):
            return rep
    if mode == "logprobs" and not rep.logprobs:
        rep.problems.append("EQA_REMOTE_MODE=logprobs but the endpoint returns no logprobs: set "
                            "EQA_REMOTE_MODE=sampling (or auto)")
        return rep
    rep.mode = "logprobs" if (rep.logprobs and mode != "sampling") else "sampling"
    if score_step:
        _probe_step(rep, api_key, timeout_s, samples, temperature)
    return rep
