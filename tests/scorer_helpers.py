"""Shared by the scorer tests: requests with a small synthetic labelled frame, replica subprocesses."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np

from eqa.messages import InstanceLabel, PromptPoint, Question, ScoreRequest
from eqa.settings import Settings

REPO = Path(__file__).resolve().parents[1]


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
