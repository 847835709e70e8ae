"""Shared by the scorer tests: requests with a small synthetic labelled frame, replica subprocesses."""

from __future__ import annotations

import contextlib
import os
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from eqa.bus import Bus
from eqa.messages import InstanceLabel, PromptPoint, Question, ScoreRequest
from eqa.scorer_client import ScorerClient
from eqa.settings import Settings
from services.vlm_scorer.service import ScorerService

REPO = Path(__file__).resolve().parents[2]


@contextlib.contextmanager
def scorer_pool(hub_settings: Settings, *replicas: Settings) -> Iterator[tuple[ScorerClient, list[ScorerService]]]:
    """In-process scorer replicas (one per ``replicas`` settings) and a pool client (10 s per request) on a bus of
    its own that has seen every replica live; the replicas are stopped on the way out."""
    with Bus(hub_settings, "gateway", "client") as bus:
        services = [ScorerService(s) for s in replicas]
        for svc in services:
            svc.start()
        try:
            client = ScorerClient(bus, replicas[0], timeout_s=10)
            assert client.wait_for_replicas(len(services), timeout=10)
            yield client, services
        finally:
            for svc in services:
                svc.stop()


def frame_request(
    step: int = 0,
    h: int = 60,
    w: int = 80,
    episode: str = "ep1",
    seed: int = 0,
    question: Question | None = None,
    with_target: bool = True,
) -> ScoreRequest:
    """A frame: kitchen floor on the left, living-room floor on the right, a red sofa on the right."""
    inst = np.full((h, w), 3, np.int32)  # wall
    inst[h // 2 :, : w // 2] = 1
    inst[h // 2 :, w // 2 :] = 2
    labels = [
        InstanceLabel(id=1, category="floor", room="r1", room_kind="kitchen"),
        InstanceLabel(id=2, category="floor", room="r2", room_kind="living_room"),
        InstanceLabel(id=3, category="wall", room="r1", room_kind="kitchen"),
    ]
    if with_target:
        inst[int(h * 0.6) : int(h * 0.85), int(w * 0.6) : int(w * 0.85)] = 7
        labels.append(
            InstanceLabel(
                id=7, category="sofa", room="r2", room_kind="living_room", attributes={"color": "red"}
            )
        )
    for lab in labels:
        lab.pixels = int((inst == lab.id).sum())
    q = question or Question(
        id=f"q-{episode}",  # the oracle's draws are seeded per (seed, question id, step)
        text="What color is the sofa?",
        choices=["Blue", "Red", "Green", "White"],
        scene="s0",
        query={"type": "identification", "category": "sofa"},
    )
    rgb = (np.random.default_rng(step).random((h, w, 3)) * 255).astype(np.uint8)
    pts = [
        PromptPoint(label="A", x=0, y=0, u=w * 0.25, v=h * 0.8),
        PromptPoint(label="B", x=1, y=0, u=w * 0.72, v=h * 0.8),
    ]
    return ScoreRequest(
        episode_id=episode,
        step=step,
        question=q,
        rgb=rgb,
        prompt_points=pts,
        instances=inst,
        labels=labels,
        depth=np.full((h, w), 2.0, np.float32),
        seed=seed,
    )


def start_replica(settings: Settings, replica: str, **env: str) -> subprocess.Popen[bytes]:
    """``python -m services.vlm_scorer`` as a separate process with the given settings."""
    full = {
        **os.environ,
        **settings.env(),
        "EQA_SCORER_REPLICA": replica,
        "EQA_INSTANCE": replica,
        "EQA_LOG_LEVEL": "WARNING",
        **env,
    }
    return subprocess.Popen(
        [sys.executable, "-m", "services.vlm_scorer"],
        cwd=REPO,
        env=full,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
    )


# ---- an OpenAI-compatible chat-completions double (real HTTP on loopback), logprobs on or off ---------------
# Its "model" has a fixed next-token distribution per prompt kind; with logprobs on it returns the top list
# like vLLM, with logprobs off it ignores the fields like `transformers serve` and answers sampled text.
DOUBLE_DISTRIBUTIONS: dict[str, list[tuple[str, float]]] = {
    "yesno": [("Yes", 0.3), ("No", 0.6), ("Maybe", 0.1)],
    "letter": [("A", 0.2), ("B", 0.7), ("x", 0.1)],
    "answer": [("B", 0.6), ("A", 0.2), ("C", 0.1), ("hmm", 0.1)],
}


def double_kind(text: str) -> str:
    if "Yes or No" in text:
        return "yesno"
    if "single letter" in text:
        return "letter"
    return "answer"


class OpenAIDouble:
    """Behaviour of the double: ``logprobs`` (return them or ignore the fields), ``n`` ("honour", "ignore":
    one choice whatever n, "refuse": HTTP 400 for n > 1), ``image`` (False: 400 for image content)."""

    def __init__(self, logprobs: bool = True, n: str = "honour", image: bool = True, seed: int = 0,
                 models: tuple[str, ...] = ("tiny-vlm",)) -> None:
        import threading

        self.logprobs = logprobs
        self.n = n
        self.image = image
        self.models = models
        self.rng = np.random.default_rng(seed)
        self.requests: list[dict] = []
        self.lock = threading.Lock()

    def chat(self, body: dict) -> tuple[int, dict]:
        with self.lock:
            self.requests.append(body)
        content = body["messages"][-1]["content"]
        if not self.image and any(c.get("type") == "image_url" for c in content):
            return 400, {"error": {"message": "this model does not accept images"}}
        text = content[-1]["text"]
        n = int(body.get("n", 1))
        if n > 1 and self.n == "refuse":
            return 400, {"error": {"message": "only n=1 is supported"}}
        if n > 1 and self.n == "ignore":
            n = 1
        if body.get("max_tokens", 1) > 3:  # a proposal (VI-A)
            return 200, {"choices": [{"index": 0, "message": {"role": "assistant", "content": "Red\nBlue"}}]}
        dist = DOUBLE_DISTRIBUTIONS[double_kind(text)]
        toks = [t for t, _ in dist]
        probs = np.array([p for _, p in dist])
        choices = []
        for i in range(n):
            if body.get("temperature", 1.0) == 0:
                tok = toks[int(np.argmax(probs))]
            else:
                with self.lock:
                    tok = toks[int(self.rng.choice(len(toks), p=probs))]
            choice: dict = {"index": i, "message": {"role": "assistant", "content": tok}, "finish_reason": "length"}
            if self.logprobs and body.get("logprobs"):
                import math

                choice["logprobs"] = {"content": [{
                    "token": tok, "logprob": math.log(dict(dist)[tok]),
                    "top_logprobs": [{"token": t, "logprob": math.log(p)} for t, p in dist],
                }]}
            choices.append(choice)
        return 200, {"object": "chat.completion", "model": body.get("model"), "choices": choices}


def serve_double(double: OpenAIDouble) -> tuple[str, object]:
    """Start the double on a free loopback port: ``(base_url ending in /v1, server)``; stop with
    ``server.shutdown(); server.server_close()``."""
    import json
    import threading
    from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

    class Handler(BaseHTTPRequestHandler):
        def _send(self, status: int, out: dict) -> None:
            data = json.dumps(out).encode()
            self.send_response(status)
            self.send_header("Content-Type", "application/json")
            self.send_header("Content-Length", str(len(data)))
            self.end_headers()
            self.wfile.write(data)

        def do_GET(self) -> None:
            if self.path == "/v1/models":
                self._send(200, {"object": "list", "data": [{"id": m, "object": "model"} for m in double.models]})
            else:
                self._send(404, {"error": "not found"})

        def do_POST(self) -> None:
            if self.path != "/v1/chat/completions":
                self._send(404, {"error": "not found"})
                return
            body = json.loads(self.rfile.read(int(self.headers["Content-Length"])))
            self._send(*double.chat(body))

        def log_message(self, *args: object) -> None:
            pass

    httpd = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
    httpd.daemon_threads = True
    threading.Thread(target=httpd.serve_forever, daemon=True).start()
    return f"http://127.0.0.1:{httpd.server_address[1]}/v1", httpd


# ---- transformers serve (the real OpenAI-compatible server; its own venv, scripts/setup-serve.sh) ----------
VENV_SERVE = Path(os.environ.get("VENV_SERVE", REPO / "var" / "venv-serve"))


def serve_installed() -> bool:
    return any(VENV_SERVE.glob(".serve-installed-*")) and (VENV_SERVE / "bin" / "transformers").exists()


def install_serve(timeout_s: float = 1500) -> tuple[bool, str]:
    """Run scripts/setup-serve.sh (guarded, quick when installed): ``(ok, last lines of its output)``."""
    proc = subprocess.run(
        ["bash", str(REPO / "scripts" / "setup-serve.sh")],
        cwd=REPO, env={**os.environ, "VENV_SERVE": str(VENV_SERVE)},
        capture_output=True, text=True, timeout=timeout_s, check=False,
    )
    return proc.returncode == 0 and serve_installed(), (proc.stderr or proc.stdout)[-600:]


def start_serve(model_dir: Path, log_path: Path, timeout_s: float = 180.0) -> tuple[subprocess.Popen[bytes], str, str]:
    """``transformers serve MODEL_DIR`` (the model preloaded and pinned: requests must name it by this path) on
    a free loopback port, waited for (``GET /health``): ``(process, base_url, model id)``. RuntimeError with the
    server's log if it does not come up. Its ``GET /v1/models`` lists the Hugging Face cache, not the pinned
    model: an empty cache directory is given (without one, transformers 5.23 answers that call with a 500)."""
    import time

    import httpx

    from eqa.launcher import free_port

    port = free_port()
    cache = log_path.parent / "hf-cache"
    cache.mkdir(parents=True, exist_ok=True)
    env = {**os.environ, "HF_HUB_OFFLINE": "1", "TRANSFORMERS_OFFLINE": "1", "OMP_NUM_THREADS": "1",
           "HF_HUB_CACHE": str(cache)}
    with log_path.open("wb") as log_file:
        proc = subprocess.Popen(
            [str(VENV_SERVE / "bin" / "transformers"), "serve", str(model_dir), "--host", "127.0.0.1",
             "--port", str(port), "--device", "cpu", "--log-level", "info"],
            env=env, stdout=log_file, stderr=subprocess.STDOUT,
        )
    url = f"http://127.0.0.1:{port}/v1"
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline and proc.poll() is None:
        try:
            if httpx.get(f"http://127.0.0.1:{port}/health", timeout=2).status_code == 200:
                return proc, url, str(model_dir)
        except httpx.HTTPError:
            pass
        time.sleep(0.5)
    stop_process(proc)
    raise RuntimeError(f"transformers serve did not come up: {log_path.read_text(errors='replace')[-1500:]}")


def stop_process(proc: subprocess.Popen[bytes]) -> None:
    proc.terminate()
    try:
        proc.wait(timeout=15)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait(timeout=10)


# ---- llama.cpp's llama-server (built from source with a tiny GGUF by scripts/setup-llama.sh) ---------------
LLAMA_ALIAS = "tiny-llava"


def setup_llama(timeout_s: float = 3600) -> tuple[dict[str, str] | None, bool, str]:
    """Run scripts/setup-llama.sh (guarded, quick when done): ``(paths, built, last lines of its messages)``;
    paths has LLAMA_SERVER, LLAMA_MODEL, LLAMA_MMPROJ, or is None when the set-up failed; ``built`` is False when
    it was the server that could not be had (the script's exit status 1; 2 is a failed GGUF conversion)."""
    proc = subprocess.run(["bash", str(REPO / "scripts" / "setup-llama.sh")], cwd=REPO, capture_output=True,
                          text=True, timeout=timeout_s, check=False)
    paths = dict(line.split("=", 1) for line in proc.stdout.splitlines() if line.startswith("LLAMA_"))
    ok = proc.returncode == 0 and all(Path(paths.get(k, "")).is_file()
                                      for k in ("LLAMA_SERVER", "LLAMA_MODEL", "LLAMA_MMPROJ"))
    return (paths if ok else None), proc.returncode != 1, proc.stderr[-800:]


def start_llama_server(paths: dict[str, str], log_path: Path, mmproj: bool = True,
                       timeout_s: float = 120.0) -> tuple[subprocess.Popen[bytes], str, str]:
    """``llama-server`` with the tiny GGUF (and its vision projector unless ``mmproj=False``) on a free loopback
    port, waited for (``GET /health``): ``(process, base_url, model id)``. RuntimeError with its log if it does
    not come up. One thread: the machine's cores are shared, and the tiny model needs no more."""
    import time

    import httpx

    from eqa.launcher import free_port

    port = free_port()
    cmd = [paths["LLAMA_SERVER"], "-m", paths["LLAMA_MODEL"], "--host", "127.0.0.1", "--port", str(port),
           "--alias", LLAMA_ALIAS, "--jinja", "-c", "4096", "-t", "1", "--no-webui"]
    if mmproj:
        cmd += ["--mmproj", paths["LLAMA_MMPROJ"]]
    with log_path.open("wb") as log_file:
        proc = subprocess.Popen(cmd, stdout=log_file, stderr=subprocess.STDOUT)
    url = f"http://127.0.0.1:{port}/v1"
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline and proc.poll() is None:
        try:
            if httpx.get(f"http://127.0.0.1:{port}/health", timeout=2).status_code == 200:
                return proc, url, LLAMA_ALIAS
        except httpx.HTTPError:
            pass
        time.sleep(0.3)
    stop_process(proc)
    raise RuntimeError(f"llama-server did not come up: {log_path.read_text(errors='replace')[-1500:]}")


def remote_fleet_episode(tmp_path: Path, url: str, model: str, mode: str, **remote: object) -> None:
    """One 3-step benchmark question through a real fleet (sim, mapper, planner, stopper, a scorer replica as
    separate processes) whose scorer is the remote backend on the server at ``url``; every step must have been
    scored in ``mode`` ("logprobs" or "sampling") with a probability vector over the question's choices."""
    from eqa_app.benchmark_runner import Runner
    from services.sim.questions import benchmark

    s = Settings(data_dir=tmp_path, zenoh_listen=[], zenoh_connect=[], sim_width=160, sim_height=120,
                 scorer_backend="remote", remote_base_url=url, remote_model=model, remote_timeout_s=120.0,
                 scorer_timeout_s=300.0, **remote)  # type: ignore[arg-type]
    question = benchmark(seed=0, scenes_dir=s.scenes_path).calibration[0].model_copy(update={"max_steps": 3})
    with Runner(s, robots=1, scorers=1, step_timeout_s=240) as runner:
        results = list(runner.run([question]))
    assert len(results) == 1
    res = results[0]
    assert res.end is not None and not res.reason.startswith("failed"), res.reason
    assert res.steps and [st.step for st in res.steps] == list(range(len(res.steps)))
    modes = {st.mode for st in res.steps} - {""}  # steps filled in from the stopper's stored trace carry none
    assert modes == {mode}, modes
    for st in res.steps:
        assert len(st.answer_probs) == len(question.choices) and abs(sum(st.answer_probs) - 1) < 1e-6
