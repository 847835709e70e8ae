"""HTTP request / response bodies of the gateway (pydantic v2). The stored episode record and the status
response is :class:`eqa.messages.EpisodeStatus`."""

from __future__ import annotations

from typing import Annotated

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from eqa import keys
from eqa.messages import (
    MAX_CHOICES,
    EpisodeState,
    EpisodeStatus,
    Pose2D,
    StopConfig,
    StopRule,
    Strategy,
    letters,
)

MAX_QUESTION_CHARS = 2000
MAX_CHOICE_CHARS = 300

_EXAMPLE = {
    "question": "Where did I leave the black suitcase?",
    "choices": ["bedroom", "hallway", "storage room", "living room"],
    "scene": "gen-house-7",
    "strategy": "semantic",
    "stop_rule": "cp",
    "eps": 0.2,
    "max_steps": 30,
}


class QuestionRequest(BaseModel):
    """A question for one robot. Give a ``scene`` (simulated robots load or generate it), a ``robot`` id, or
    both; without ``robot`` the gateway picks a free robot (or queues, per ``EQA_BUSY_POLICY``)."""

    model_config = ConfigDict(
        extra="forbid",
        json_schema_extra={
            "examples": [
                _EXAMPLE,
                {
                    "question": "Is the stove turned on?",
                    "robot": "robot0",
                    "scene": "gen-house-2",
                    "start_pose": {"x": 1.5, "y": 2.0, "yaw": 0.0},
                    "stop_rule": "relevance",
                    "threshold": 0.6,
                },
            ]
        },
    )
    question: Annotated[str, Field(min_length=1, max_length=MAX_QUESTION_CHARS, description="the question text")]
    choices: list[Annotated[str, Field(min_length=1, max_length=MAX_CHOICE_CHARS)]] | None = Field(
        default=None, description=f"2..{MAX_CHOICES} answer choices (labelled A, B, ...), or none"
    )
    scene: Annotated[str, Field(min_length=1, max_length=200)] | None = Field(
        default=None, description="scene name for the simulator (generated scenes: any name; HM3D: scene id)"
    )
    robot: str | None = Field(default=None, description="robot id (one of EQA_ROBOTS); default: any free robot")
    start_pose: Pose2D | None = Field(default=None, description="initial pose; default: sampled by the sim")
    strategy: Strategy = Field(default="semantic", description="exploration strategy")
    stop_rule: StopRule = Field(default="cp", description="stopping rule (cp = multi-step conformal prediction)")
    eps: float = Field(default=0.2, gt=0.0, lt=1.0, description="CP miscoverage level: 1-eps coverage wanted")
    threshold: float | None = Field(default=None, description="entropy (nats) or relevance threshold")
    max_steps: int | None = Field(
        default=None, ge=1, le=10_000, description="step budget; default 3*sqrt(floor area) (Explore-EQA VI)"
    )
    seed: int = Field(default=0, ge=0, le=2**31 - 1, description="seed of the start pose sampling")
    record: bool = Field(default=True, description="write a Rerun recording of the episode")
    answer: str | None = Field(default=None, description="ground-truth letter (benchmarks only; scorers never read it)")
    question_id: str | None = Field(
        default=None,
        description="your id for this question (e.g. a benchmark question id); default: a new one. The oracle "
        "scorer seeds its draws with it, so the same id, scene and seed replay the same episode",
    )

    @field_validator("question")
    @classmethod
    def _not_blank(cls, v: str) -> str:
        if not v.strip():
            raise ValueError("question text is empty")
        return v

    @field_validator("choices")
    @classmethod
    def _choice_count(cls, v: list[str] | None) -> list[str] | None:
        if v is not None and v and not 2 <= len(v) <= MAX_CHOICES:
            raise ValueError(f"give between 2 and {MAX_CHOICES} choices (or none), got {len(v)}")
        return v or None

    @field_validator("robot")
    @classmethod
    def _robot_id(cls, v: str | None) -> str | None:
        return None if v is None else keys.check_id(v, "robot")

    @field_validator("question_id")
    @classmethod
    def _question_id(cls, v: str | None) -> str | None:
        return None if v is None else keys.check_id(v, "question_id")

    @model_validator(mode="after")
    def _scene_or_robot(self) -> QuestionRequest:
        if self.scene is None and self.robot is None:
            raise ValueError("give a scene, a robot id, or both")
        if self.answer is not None and (not self.choices or self.answer not in letters(len(self.choices))):
            raise ValueError(f"answer {self.answer!r} is not one of the choice letters")
        return self

    def stop_config(self) -> StopConfig:
        return StopConfig(rule=self.stop_rule, eps=self.eps, threshold=self.threshold)


class Submitted(BaseModel):
    """The answer to a submitted question."""

    episode_id: str
    robot: str
    state: EpisodeState
    max_steps: int
    queue_position: int = Field(default=0, description="0 = running now; n = n-th in the robot's queue")
    links: dict[str, str] = Field(default_factory=dict)


class EpisodeList(BaseModel):
    episodes: list[EpisodeStatus]


class Health(BaseModel):
    status: str = "ok"
    instance: str


class Readiness(BaseModel):
    ready: bool
    store: bool
    bus: bool
    services: dict[str, list[str]] = Field(description="alive instances per service (liveliness tokens)")
    missing: list[str] = Field(default_factory=list, description="services with no alive instance")
    robots: dict[str, str | None] = Field(default_factory=dict, description="episode running on each robot")
