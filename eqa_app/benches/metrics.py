"""What the metrics cost: one step of the episode-service kernel with counting off and on, and each hook alone.

A step here is the kernel's own share of every step of a stateful service, on real parts: a probe
:class:`eqa.episode_service.EpisodeService` over a real Zenoh session and the embedded SQLite store takes a
``StepScores`` message: ownership, the step claim in the store (sharding on), the handler (one counter update),
the state saved to the store and a ``Decision`` published -- everything but the service's own computation,
which is milliseconds to seconds (sim render, mapper TSDF + scorer round trip). With counting on, that path
goes through the step-latency histogram, the claim counter and ~6 timed store calls. Off and on alternate in
rounds (same process, same store) so that drift of the machine's load hits both alike; the figures are the
median over rounds of each round's mean per step, in microseconds, and the hooks' own costs from timeit.

    python -m eqa_app.benches.metrics [--steps 300] [--rounds 8]
"""

from __future__ import annotations

import os
import statistics
import tempfile
import threading
import time
import timeit
from pathlib import Path
from typing import Any

from eqa import keys, metrics
from eqa.episode_service import EpisodeService
from eqa.launcher import free_port
from eqa.messages import Decision, EpisodeStart, Question, StepScores
from eqa.settings import Settings
from eqa.store import EmbeddedStore
from eqa_app.benches import harness


class Probe(EpisodeService[dict[str, Any]]):
    name = "probe"

    def setup_episodes(self) -> None:
        self.on_step(keys.MAPPER_SCORES, self.on_scores)

    def start_episode(self, robot: str, start: EpisodeStart) -> dict[str, Any] | None:
        return {"n": 0}

    def dump_state(self, state: dict[str, Any], **extra: Any) -> dict[str, Any]:
        return dict(state)

    def load_state(self, episode_id: str, data: Any) -> dict[str, Any]:
        return {"n": int(data["n"])}

    def on_scores(self, robot: str, state: dict[str, Any], msg: StepScores) -> None:
        state["n"] += 1
        out = Decision(episode_id=msg.episode_id, step=msg.step, rule="max_steps", stop=False, reason="")
        self.publish_step(msg.episode_id, keys.STOPPER_DECISION, out, msg.step, save=True)


def run_round(svc: Probe, eid: str, steps: int) -> float:
    """Mean seconds per step over ``steps`` steps of a new episode."""
    question = Question(text="Is it on?", choices=["yes", "no"], scene="gen-00001")
    svc.receive(keys.EPISODE_START, "r0",
                EpisodeStart(episode_id=eid, robot="r0", question=question, max_steps=steps + 1, record=False))
    msgs = [StepScores(episode_id=eid, step=k, answer_probs=[0.5, 0.5], relevance=0.5) for k in range(steps)]
    t0 = time.perf_counter()
    for m in msgs:
        svc.receive(keys.MAPPER_SCORES, "r0", m)
    dt = (time.perf_counter() - t0) / steps
    svc.drop(eid, upto_step=steps)
    return dt


def hook_costs(store: EmbeddedStore) -> dict[str, tuple[float, float]]:
    """Nanoseconds per call of each hook, counting off and on."""
    out: dict[str, tuple[float, float]] = {}
    store.set("bench:k", b"v")
    cases = {
        "inc(counter)": lambda: metrics.inc(metrics.RESENDS, "probe", "frame"),
        "with timer(histogram)": lambda: metrics.timer(metrics.STEP_SECONDS, "probe", "x").__enter__().__exit__(),
        "store.get (SQLite, timed)": lambda: store.get("bench:k"),
    }
    for name, fn in cases.items():
        res = []
        for on in (False, True):
            metrics.enable(on)
            n = 20_000 if "store" not in name else 5_000
            res.append(min(timeit.repeat(fn, number=n, repeat=5)) / n * 1e9)
        out[name] = (res[0], res[1])
    metrics.enable(False)
    return out


def main(argv: list[str] | None = None) -> int:
    parser = harness.parser(__doc__)
    parser.add_argument("--steps", type=int, default=300, help="steps per round")
    parser.add_argument("--rounds", type=int, default=8, help="rounds of each (off and on alternate)")
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        settings = Settings(data_dir=Path(tmp), zenoh_mode="peer", zenoh_listen=[f"tcp/127.0.0.1:{free_port()}"],
                            zenoh_connect=[], zenoh_multicast=False, record=False)
        svc = Probe(settings)
        svc.start()
        try:
            run_round(svc, "ep-warm", 50)
            per: dict[bool, list[float]] = {False: [], True: []}
            for r in range(args.rounds):
                for on in ((False, True) if r % 2 == 0 else (True, False)):
                    metrics.enable(on)
                    per[on].append(run_round(svc, f"ep-{r}-{int(on)}", args.steps))
            metrics.enable(False)
            costs = hook_costs(EmbeddedStore(Path(tmp) / "hooks.sqlite"))
        finally:
            svc.stop()
    off, on = statistics.median(per[False]) * 1e6, statistics.median(per[True]) * 1e6
    print(f"machine load (1/5/15 min): {' '.join(os.getloadavg().__repr__().strip('()').split(', '))}")
    print(f"kernel step (claim + handler + save + publish), {args.rounds} rounds x {args.steps} steps, "
          "median of round means:")
    print(f"  metrics off: {off:8.1f} us/step   (rounds: {', '.join(f'{x * 1e6:.0f}' for x in per[False])})")
    print(f"  metrics on:  {on:8.1f} us/step   (rounds: {', '.join(f'{x * 1e6:.0f}' for x in per[True])})")
    print(f"  on - off:    {on - off:8.1f} us/step ({(on - off) / off * 100:+.1f} % of the kernel's share of a step)")
    print("hooks alone (best of 5, ns per call): off / on")
    for name, (a, b) in costs.items():
        print(f"  {name:28s} {a:8.0f} / {b:8.0f}")
    lock = threading.Lock()

    def take() -> None:
        with lock:
            pass

    print(f"for scale, on this machine: an uncontended threading.Lock taken and released "
          f"{min(timeit.repeat(take, number=20_000, repeat=5)) / 20_000 * 1e9:.0f} ns "
          "(prometheus-client takes one or two per observation)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
