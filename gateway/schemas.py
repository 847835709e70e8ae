"""HTTP request / response bodies of the gateway (pydantic v2). The stored episode record and the status
response is :class:`eqa.messages.EpisodeStatus`."""

from __future__ import annotations

from typing import Annotated

from pydantic import BaseModel, ConfigDict, Field, StrictBool, field_validator, model_validator

from eqa import keys
from eqa.messages import (
    BOUND_STRATEGIES,
    EPS_GT,
    EPS_LT,
    MAX_CHOICES,
    SCENE_ID,
    EpisodeState,
    EpisodeStatus,
    Pose2D,
    StopConfig,
    StopRule,
    Strategy,
    check_choices,
    check_scene_id,
    check_text,
    letters,
)

MAX_QUESTION_CHARS = 2000
MAX_CHOICE_CHARS = 300
HomeName = Annotated[str, Field(min_length=1, max_length=64, pattern=r"^[A-Za-z0-9_-]+$")]
HOME_DESCRIPTION = ("your name of the home (house) the robot is in: the episode reads and extends that home's memory "
                    "(GET /v1/homes/{name}); a new name makes a new home of this token. Default: no memory")


def check_home(value: str | None) -> str | None:
    """A request's ``home`` name by the id rule (:func:`eqa.keys.check_id`), or None."""
    return None if value is None else keys.check_id(value, "home")

_EXAMPLE = {
    "question": "Where did I leave the black suitcase?",
    "choices": ["bedroom", "hallway", "storage room", "living room"],
    "scene": "gen-7",
    "strategy": "semantic",
    "stop_rule": "cp",
    "eps": 0.2,
    "max_steps": 30,
}
_EXAMPLE_POSE = {
    "question": "Is the stove turned on?",
    "robot": "robot0",
    "scene": "gen-2",
    "start_pose": {"x": 9.3, "y": 13.9, "yaw": 0.0},  # free floor of gen-2 (the sim refuses a pose in a wall)
    "stop_rule": "relevance",
    "threshold": 0.6,
}


def strict_pose(value: object) -> object:
    """A request's ``start_pose`` with JSON numbers only (``{"x": "9.3"}`` and ``{"x": true}`` are refused;
    :class:`Pose2D` itself converts, as a bus message it reads numbers of any kind)."""
    if isinstance(value, dict):
        for name, v in value.items():
            if isinstance(v, bool) or not isinstance(v, int | float):
                raise ValueError(f"start_pose.{str(name)[:20]} must be a number, got {type(v).__name__}")
    return value


class QuestionRequest(BaseModel):
    """A question for one robot. Give a ``scene`` (simulated robots load or generate it), a ``robot`` id, or
    both; without ``robot`` the gateway picks a free robot (or queues, per ``EQA_BUSY_POLICY``).

    Every field is checked here, once: numbers finite and in range, texts bounded and free of NUL and other
    control characters, choices distinct, ids by one strict pattern (matched whole: no trailing newline),
    types strict (a number is a JSON number, never ``"0.2"`` or ``true``; a boolean is ``true``/``false``, never
    ``0``), texts not blank (spaces and invisible format characters alone are blank), ``choices`` absent or
    2..26 of them. The bus messages built from it are checked again by the services that receive them
    (:mod:`eqa.messages`)."""

    model_config = ConfigDict(extra="forbid", strict=True,
                              json_schema_extra={"examples": [_EXAMPLE, _EXAMPLE_POSE]})
    question: Annotated[str, Field(min_length=1, max_length=MAX_QUESTION_CHARS, description="the question text")]
    choices: list[Annotated[str, Field(min_length=1, max_length=MAX_CHOICE_CHARS)]] | None = Field(
        default=None,
        max_length=MAX_CHOICES,
        description=f"2..{MAX_CHOICES} distinct answer choices (labelled A, B, ...), or none",
    )
    scene: Annotated[str, Field(min_length=1, max_length=64, pattern=f"^{SCENE_ID.pattern}$")] | None = Field(
        default=None, description="scene id: gen-<seed> (a generated house) or an installed scene (HM3D id)"
    )
    robot: Annotated[str, Field(min_length=1, max_length=64, pattern=r"^[A-Za-z0-9_-]+$")] | None = Field(
        default=None, description="robot id (one of EQA_ROBOTS); default: any free robot"
    )
    start_pose: Pose2D | None = Field(default=None, description="initial pose; default: sampled by the sim")
    strategy: Strategy = Field(
        default="semantic",
        description=f"exploration strategy ({', '.join(sorted(BOUND_STRATEGIES))}: benchmark yardsticks, refused)",
    )
    stop_rule: StopRule = Field(default="cp", description="stopping rule (cp = multi-step conformal prediction)")
    eps: float = Field(
        default=0.2, gt=EPS_GT, lt=EPS_LT, allow_inf_nan=False,
        description="CP miscoverage level: 1-eps coverage wanted",
    )
    threshold: float | None = Field(
        default=None, ge=0.0, le=100.0, allow_inf_nan=False, description="entropy (nats) or relevance threshold"
    )
    max_steps: int | None = Field(
        default=None, ge=1, le=10_000, description="step budget; default 3*sqrt(floor area) (Explore-EQA VI)"
    )
    seed: int = Field(default=0, ge=0, le=2**31 - 1, description="seed of the start pose sampling")
    record: StrictBool = Field(default=True, description="write a Rerun recording of the episode")
    answer: Annotated[str, Field(pattern=r"^[A-Z]$")] | None = Field(
        default=None, description="ground-truth letter (benchmarks only; scorers never read it)"
    )
    question_id: Annotated[str, Field(min_length=1, max_length=64, pattern=r"^[A-Za-z0-9_-]+$")] | None = Field(
        default=None,
        description="your id for this question (e.g. a benchmark question id); default: a new one. The oracle "
        "scorer seeds its draws with it, so the same id, scene and seed replay the same episode",
    )
    home: HomeName | None = Field(default=None, description=HOME_DESCRIPTION)

    @field_validator("question")
    @classmethod
    def _not_blank(cls, v: str) -> str:
        return check_text(v, "question text")

    @field_validator("choices")
    @classmethod
    def _choice_count(cls, v: list[str] | None) -> list[str] | None:
        if v is None:
            return None
        if not v:
            raise ValueError(f"give 2..{MAX_CHOICES} choices, or leave choices out for an open question")
        return check_choices(v)

    @field_validator("start_pose", mode="before")
    @classmethod
    def _pose_numbers(cls, v: object) -> object:
        return strict_pose(v)

    @field_validator("strategy")
    @classmethod
    def _product_strategy(cls, v: str) -> str:
        if v in BOUND_STRATEGIES:
            raise ValueError(f"strategy {v!r} is a benchmark yardstick that reads the ground truth: only eqa bench "
                             "runs it")
        return v

    @field_validator("scene")
    @classmethod
    def _scene(cls, v: str | None) -> str | None:
        return None if v is None else check_scene_id(v)

    @field_validator("robot")
    @classmethod
    def _robot_id(cls, v: str | None) -> str | None:
        return None if v is None else keys.check_id(v, "robot")

    @field_validator("question_id")
    @classmethod
    def _question_id(cls, v: str | None) -> str | None:
        return None if v is None else keys.check_id(v, "question_id")

    @field_validator("home")
    @classmethod
    def _home(cls, v: str | None) -> str | None:
        return check_home(v)

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
    """Without a token (when tokens are configured) only ``ready``; with one, the details (a non-admin token
    sees the id of its own episode on a robot and ``"busy"`` for another tenant's)."""

    ready: bool
    store: bool | None = None
    bus: bool | None = None
    services: dict[str, list[str]] | None = Field(
        default=None, description="alive instances per service (liveliness tokens)"
    )
    missing: list[str] | None = Field(default=None, description="services with no alive instance")
    robots: dict[str, str | None] | None = Field(default=None, description="episode running on each robot")


class FieldError(BaseModel):
    loc: list[str | int]
    msg: str
    type: str


class Problem(BaseModel):
    """Every error answer: ``detail`` says what to change (a text, or one entry per invalid field)."""

    detail: str | list[FieldError]
