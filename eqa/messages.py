"""Typed messages of the bus (schema version 1).

Conventions used by every service:

* World frame: metres, ``x``/``y`` horizontal, ``z`` up, the floor of the current storey at ``z = 0``.
* :class:`Pose2D` is the robot base: position ``(x, y)`` and heading ``yaw`` (radians, counter-clockwise
  from ``+x``).
* Camera poses are 4x4 camera-to-world matrices in the OpenCV camera convention (``x`` right, ``y`` down,
  ``z`` forward); intrinsics are 3x3 pinhole matrices in pixels.
* Answers are letters ``A``, ``B``, ... indexing :attr:`Question.choices`.
* A step ``t`` is one stop of the robot with one frame; steps count from 0; ``max_steps`` frames at most.

Every message carries ``kind`` and ``schema_version``; :func:`encode` / :func:`decode` put them on the
wire with msgpack (see :mod:`eqa.codec`). A decoder refuses a newer major schema with a clear error.
"""

from __future__ import annotations

import math
import re
import string
import time
import unicodedata
import uuid
from typing import Annotated, Any, ClassVar, Literal, TypeVar

import numpy as np
from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    StrictBool,
    StrictFloat,
    StrictInt,
    ValidationError,
    field_validator,
    model_validator,
)

from eqa import keys
from eqa.codec import CodecError, NDArray, ZNDArray, packb, unpackb

SCHEMA_VERSION = 1
LETTERS = string.ascii_uppercase
MAX_CHOICES = len(LETTERS)
PADDING_CHOICE = "(Do not choose this option)"
NOT_LISTED_CHOICE = "An option not listed here"

Strategy = Literal["fbe", "semantic", "no_lsv", "no_gsv", "nearest", "target_oracle", "perfect_sv", "cp_guided",
                   "vlfm", "gain", "topo", "perfect_vlfm", "perfect_gain"]
# Perfect-value yardsticks -> the product strategy whose choice rule they run: the mapper writes the LSV / GSV
# of the ground truth (services.mapper.semantic_map.ground_truth_scores) in place of the scorer's, the planner
# applies that strategy's rule unchanged, so the pair separates what the values cost from what the rule costs.
PERFECT_VALUE_RULE: dict[str, str] = {"perfect_sv": "semantic", "perfect_vlfm": "vlfm", "perfect_gain": "gain"}
# Benchmark-only yardsticks (upper bounds, never product behaviour): they read the question's ground truth
# (``Question.targets``). The gateway and the CLI refuse them; only ``eqa bench`` runs them.
BOUND_STRATEGIES: frozenset[str] = frozenset({"target_oracle", *PERFECT_VALUE_RULE})
StopRule = Literal["cp", "entropy", "relevance", "max_steps"]
# The CP miscoverage level eps (Explore-EQA Eq. 10: 1 - eps is the success wanted) lies in the open interval
# (EPS_GT, EPS_LT): at 0 the quantile rank ceil((N+1)(1-eps)) exceeds every N, at 1 nothing is covered. The bus,
# the gateway's request schema and the calibration all check these bounds.
EPS_GT = 0.0
EPS_LT = 1.0
EpisodeState = Literal["queued", "running", "stopped", "failed", "cancelled"]
ScorerBackend = Literal["oracle", "hf", "remote"]


MAX_COORD_M = 100_000.0  # |x|, |y| of a pose (metres): far past any building; 1e308 overflowed the sim's grid
MAX_YAW_RAD = 10_000.0
SCENE_ID = re.compile(r"[A-Za-z0-9][A-Za-z0-9_-]{0,63}")
"""A scene id: ``gen-<seed>`` or an installed scene (HM3D ``00009-vLpv2VX547B``); matched whole (``fullmatch``:
no trailing newline, no path separators or dots)."""


def eps_in_bounds(value: float) -> bool:
    """Whether ``value`` is a finite CP miscoverage level in the open interval ``(EPS_GT, EPS_LT)``."""
    return math.isfinite(value) and EPS_GT < value < EPS_LT


def check_scene_id(value: str) -> str:
    """``value`` if it is a valid scene id, else ``ValueError`` saying what one looks like."""
    if not isinstance(value, str) or not SCENE_ID.fullmatch(value):
        raise ValueError(
            f"scene {str(value)[:80]!r} is not a scene id: 1-64 letters, digits, '_' or '-' starting with a letter "
            "or digit, e.g. gen-7 (a generated house) or the id of an installed scene"
        )
    return value


def is_blank(value: str) -> bool:
    """True when ``value`` shows nothing: only white space and Unicode format characters (category Cf:
    zero-width spaces and joiners, byte-order marks, direction marks), which a reader cannot see."""
    return all(c.isspace() or unicodedata.category(c) == "Cf" for c in value)


def check_text(value: str, what: str) -> str:
    """No NUL (or other C0 control character but tab and newline) and not blank (:func:`is_blank`)."""
    if any(c < " " and c not in "\t\n\r" for c in value):
        raise ValueError(f"{what} contains a control character (NUL or similar): remove it")
    if is_blank(value):
        raise ValueError(f"{what} is empty (only spaces or invisible characters)")
    return value


def check_choices(choices: list[str]) -> list[str]:
    """2..26 choices (or none), each non-blank without control characters, no two alike (ignoring case and
    surrounding spaces) except the HM-EQA padding choice."""
    if choices and not 2 <= len(choices) <= MAX_CHOICES:
        raise ValueError(f"give between 2 and {MAX_CHOICES} choices (or none), got {len(choices)}")
    seen: set[str] = set()
    for i, c in enumerate(choices):
        check_text(c, f"choice {LETTERS[i] if i < MAX_CHOICES else i}")
        norm = c.strip().casefold()
        if norm in seen and c != PADDING_CHOICE:
            raise ValueError(f"choice {LETTERS[i]} ({c.strip()[:40]!r}) is given twice: each choice once")
        seen.add(norm)
    return choices


def letters(n: int) -> list[str]:
    """The answer labels of ``n`` choices: ``A``, ``B``, ..."""
    if not 1 <= n <= MAX_CHOICES:
        raise ValueError(f"number of choices must be 1..{MAX_CHOICES}, got {n}")
    return list(LETTERS[:n])


def new_id(prefix: str = "ep") -> str:
    return f"{prefix}-{uuid.uuid4().hex[:12]}"


class Message(BaseModel):
    """Base of every bus message."""

    model_config = ConfigDict(arbitrary_types_allowed=True, extra="forbid", frozen=False)
    kind: ClassVar[str] = "message"
    schema_version: int = SCHEMA_VERSION
    sent_at: float = Field(default_factory=time.time)


class Pose2D(BaseModel):
    model_config = ConfigDict(extra="forbid")
    x: float
    y: float
    yaw: float = 0.0

    @model_validator(mode="after")
    def _finite(self) -> Pose2D:
        if not all(math.isfinite(v) for v in (self.x, self.y, self.yaw)):
            raise ValueError("pose values must be finite numbers (no NaN or inf)")
        if abs(self.x) > MAX_COORD_M or abs(self.y) > MAX_COORD_M or abs(self.yaw) > MAX_YAW_RAD:
            raise ValueError(
                f"pose out of range: |x|, |y| at most {MAX_COORD_M:g} m and |yaw| at most {MAX_YAW_RAD:g} rad"
            )
        return self

    def xy(self) -> np.ndarray:
        return np.array([self.x, self.y], dtype=np.float64)

    @classmethod
    def parse(cls, text: str) -> Pose2D:
        """``"x,y[,yaw]"`` (metres, radians; yaw 0 when left out). ``ValueError`` says what is wrong."""
        parts = [p.strip() for p in text.split(",")]
        if len(parts) not in (2, 3):
            raise ValueError(f"pose must be x,y or x,y,yaw (numbers), got {text!r}")
        try:
            values = [float(p) for p in parts]
        except ValueError:
            raise ValueError(f"pose must be numbers like 1.5,-2,0.7, got {text!r}") from None
        if not all(math.isfinite(v) for v in values):
            raise ValueError(f"pose values must be finite, got {text!r}")
        return cls(x=values[0], y=values[1], yaw=values[2] if len(values) == 3 else 0.0)


class Question(BaseModel):
    """A question about one scene. ``answer`` and ``evidence_ids`` are ground truth, known for benchmark
    questions only; no scorer backend reads them."""

    model_config = ConfigDict(extra="forbid")
    id: str = Field(default_factory=lambda: new_id("q"))
    text: Annotated[str, Field(min_length=1, max_length=2000)]
    choices: list[Annotated[str, Field(min_length=1, max_length=300)]] = Field(default_factory=list)
    scene: str
    floor: int = 0
    category: str | None = None
    # Structured parse of what the question asks (what a language model reads from the text, never the
    # answer): keys "type" (identification|counting|existence|state|location), "category", optionally
    # "room_kind", "attribute" (e.g. "color", "state"), "value" (the asked state, e.g. "on"), "color".
    query: dict[str, str] = Field(default_factory=dict)
    answer: str | None = None
    evidence_ids: list[int] = Field(default_factory=list)
    # Ground truth for benchmark yardsticks only: floor positions (x, y) of the evidence objects (the asked
    # room's centre when no object is the evidence). Read by no scorer and by no product strategy.
    targets: list[tuple[float, float]] = Field(default_factory=list, max_length=64)
    start_pose: Pose2D | None = None
    max_steps: StrictInt | None = Field(default=None, ge=1, le=10_000)

    def without_ground_truth(self) -> Question:
        """The question as a scorer sees it: no answer, evidence ids or target positions (ground truth)."""
        return self.model_copy(update={"answer": None, "evidence_ids": [], "targets": []})

    @field_validator("text")
    @classmethod
    def _text_not_blank(cls, v: str) -> str:
        return check_text(v, "question text")

    @field_validator("choices")
    @classmethod
    def _choices_count(cls, v: list[str]) -> list[str]:
        return check_choices(v)

    @field_validator("scene")
    @classmethod
    def _scene_id(cls, v: str) -> str:
        return v if v == "" else check_scene_id(v)  # "": the robot's own world (no simulator scene)

    @model_validator(mode="after")
    def _answer_is_letter(self) -> Question:
        if self.answer is not None and self.choices and self.answer not in letters(len(self.choices)):
            raise ValueError(f"answer {self.answer!r} is not one of the choice letters")
        return self

    @property
    def labels(self) -> list[str]:
        return letters(len(self.choices)) if self.choices else []

    def formatted(self) -> str:
        """The HM-EQA prompt form: ``Q? A) x B) y ... Answer:``."""
        opts = " ".join(f"{k}) {c}" for k, c in zip(self.labels, self.choices, strict=True))
        return f"{self.text} {opts}. Answer:" if opts else f"{self.text} Answer:"


TaskKind = Literal["pick_place", "find_object"]
ClassName = Annotated[str, Field(min_length=1, max_length=80, pattern=r"^[a-z0-9][a-z0-9_ -]*$")]


class Task(BaseModel):
    """A HELIOS task (paper sections 4.1, 4.2): ``pick_place`` = "Move (object) from the (start_receptacle)
    to the (goal_receptacle)"; ``find_object`` = "Find a (object)", ended by a stop call.

    ``object``, ``start_receptacle`` and ``goal_receptacle`` are the open-vocabulary class names the planner
    and the detector work with. The ``*_ids`` and ``shortest_path_m`` are simulator ground truth for scoring
    (any listed object on a listed start receptacle counts), read by no planner or detector except the
    ground-truth-semantics ablation (Table 4)."""

    model_config = ConfigDict(extra="forbid")
    id: str = Field(default_factory=lambda: new_id("task"))
    kind: TaskKind
    text: Annotated[str, Field(min_length=1, max_length=500)]
    scene: str
    floor: int = 0
    object: ClassName
    start_receptacle: ClassName | None = None
    goal_receptacle: ClassName | None = None
    object_ids: list[int] = Field(default_factory=list, max_length=256)
    start_receptacle_ids: list[int] = Field(default_factory=list, max_length=256)
    goal_receptacle_ids: list[int] = Field(default_factory=list, max_length=256)
    start_pose: Pose2D | None = None
    max_steps: StrictInt | None = Field(default=None, ge=1, le=10_000)
    shortest_path_m: float | None = Field(default=None, ge=0.0)

    @model_validator(mode="after")
    def _receptacles_of_kind(self) -> Task:
        if self.kind == "pick_place" and (self.start_receptacle is None or self.goal_receptacle is None):
            raise ValueError("a pick_place task names a start_receptacle and a goal_receptacle")
        if self.kind == "find_object" and (self.start_receptacle is not None or self.goal_receptacle is not None):
            raise ValueError("a find_object task names only the object")
        if self.object in (self.start_receptacle, self.goal_receptacle):
            raise ValueError(f"the object ({self.object!r}) is also named as a receptacle: name the thing to move "
                             "and two other things it is on and goes to")
        return self

    @property
    def classes(self) -> list[str]:
        """The task's classes in the order object, start receptacle, goal receptacle (the detector's
        vocabulary for this episode)."""
        return [c for c in (self.object, self.start_receptacle, self.goal_receptacle) if c is not None]


TaskPhase = Literal["searching", "local_search", "looking", "picking", "placing", "finished"]
Ablation = Literal["helios", "no_global", "trusting"]
Skill = Literal["move", "pick", "place", "stop"]


class SkillReport(BaseModel):
    """What a task skill did (the sim runs it after moving to the goal's pose): the oracle pick, the
    heuristic place, or the stop call of a find-object task. Carried by the next ``Frame`` and passed on by the
    mapper in ``MapUpdate.skill`` so the planner's state machine learns the outcome."""

    model_config = ConfigDict(extra="forbid")
    skill: Literal["pick", "place", "stop"]
    success: bool
    target: int | None = None
    reason: Annotated[str, Field(max_length=300)] = ""


class StopConfig(BaseModel):
    """How an episode decides to stop (Explore-EQA section V)."""

    model_config = ConfigDict(extra="forbid")
    rule: StopRule = "cp"
    eps: StrictFloat = Field(
        default=0.2, gt=EPS_GT, lt=EPS_LT, description="CP miscoverage: 1-eps is the success wanted"
    )
    threshold: StrictFloat | None = Field(
        default=None, ge=0.0, le=100.0, allow_inf_nan=False, description="entropy (nats) or relevance threshold"
    )


class EpisodeStart(Message):
    kind: ClassVar[str] = "episode_start"
    episode_id: str
    robot: str
    question: Question
    strategy: Strategy = "semantic"
    stop: StopConfig = Field(default_factory=StopConfig)
    max_steps: StrictInt = Field(ge=1, le=10_000)
    seed: StrictInt = Field(default=0, ge=0, le=2**63 - 1)
    record: StrictBool = True
    # A HELIOS task episode when set; ``question`` is then its stand-in (text = the instruction).
    task: Task | None = None
    ablation: Ablation = "helios"
    pick_limit: int | None = Field(default=None, ge=1, le=1000)  # None = unlimited (Table 1: 1, 5, unlimited)
    # The internal id of the home whose memory the episode reads and extends (:func:`eqa.homes.home_id`);
    # None: the episode starts from an empty map and leaves no memory.
    home: str | None = None
    # The key the simulated perception models draw from, with ``seed`` and the step (:attr:`DetectRequest.draws`);
    # None: the episode id, fresh for every episode. The same key and seed repeat a run's draws.
    draws: str | None = None
    # Ground truth for the target_oracle yardstick only (set by the benchmark runners, never by the gateway):
    # the walked distance from every cell of the house to the nearest target (services/sim/paths.py).
    target_paths: TargetPaths | None = None

    @field_validator("episode_id", "robot")
    @classmethod
    def _safe(cls, v: str) -> str:
        return keys.check_id(v)

    @field_validator("home")
    @classmethod
    def _safe_home(cls, v: str | None) -> str | None:
        return None if v is None else keys.check_id(v, "home")

    @field_validator("draws")
    @classmethod
    def _safe_draws(cls, v: str | None) -> str | None:
        return None if v is None else keys.check_id(v, "draws")

    @model_validator(mode="after")
    def _paths_only_for_the_yardstick(self) -> EpisodeStart:
        if self.target_paths is not None and self.strategy != "target_oracle":
            raise ValueError(f"target_paths (ground truth) is for the target_oracle yardstick only, not for "
                             f"strategy {self.strategy!r}")
        return self


class EpisodeCancel(Message):
    kind: ClassVar[str] = "episode_cancel"
    episode_id: str
    reason: str = "cancelled by user"


class InstanceLabel(BaseModel):
    """Ground-truth label of one instance id visible in a simulated frame (what a perfect detector would
    report). Only instances with at least one pixel in the frame are listed."""

    model_config = ConfigDict(extra="forbid")
    id: int
    category: str
    room: str | None = None
    room_kind: str | None = None
    attributes: dict[str, str] = Field(default_factory=dict)
    pixels: int = 0


class Frame(Message):
    """One RGB-D observation at step ``step``."""

    kind: ClassVar[str] = "frame"
    episode_id: str
    step: int = Field(ge=0)
    pose: Pose2D
    camera_pose: NDArray  # 4x4 float64 camera-to-world
    intrinsics: NDArray  # 3x3 float64
    rgb: NDArray  # HxWx3 uint8
    depth: NDArray  # HxW float32 metres along the optical axis, 0 or inf where nothing was hit
    instances: NDArray | None = None  # HxW int32 instance ids, -1 for none (simulator only)
    labels: list[InstanceLabel] = Field(default_factory=list)
    scene: str = ""
    floor_area_m2: float | None = None
    skill: SkillReport | None = None  # the task skill run before this frame (task episodes)


class Frontier(BaseModel):
    model_config = ConfigDict(extra="forbid")
    x: float
    y: float
    nx: float  # unit normal pointing into unknown space
    ny: float
    size: int  # cells in the cluster
    weight: float = 1.0  # Eq. A6
    sv: float = 1.0
    sv_normal: float = 1.0


class PromptPoint(BaseModel):
    model_config = ConfigDict(extra="forbid")
    label: str
    x: float
    y: float
    u: float  # pixel column
    v: float  # pixel row


class GridSpec(BaseModel):
    """A 2D grid over the floor: cell ``(i, j)`` (row, column) covers
    ``x in [origin_x + j*res, +res)``, ``y in [origin_y + i*res, +res)``."""

    model_config = ConfigDict(extra="forbid")
    origin_x: float
    origin_y: float
    resolution: float = Field(gt=0)
    rows: int = Field(ge=1)
    cols: int = Field(ge=1)


MAX_TARGET_PATH_CELLS = 4_000_000  # a 200 m x 200 m house at 0.1 m per cell


class TargetPaths(BaseModel):
    """Benchmark-only ground truth of the ``target_oracle`` yardstick: ``distance_m[i, j]`` is the length (m)
    of the shortest walk through the true house from cell ``(i, j)`` of ``grid`` to the nearest target of the
    question (``inf``: none reachable). Made by the simulator side (services/sim/paths.py) from its navigable
    grid; read by the mapper to weigh frontiers for that one strategy."""

    model_config = ConfigDict(arbitrary_types_allowed=True, extra="forbid")
    grid: GridSpec
    distance_m: ZNDArray

    @model_validator(mode="after")
    def _shape(self) -> TargetPaths:
        g, d = self.grid, self.distance_m
        if g.rows * g.cols > MAX_TARGET_PATH_CELLS:
            raise ValueError(f"target paths grid {g.rows}x{g.cols} exceeds {MAX_TARGET_PATH_CELLS} cells")
        if not isinstance(d, np.ndarray) or d.dtype != np.float32 or d.shape != (g.rows, g.cols):
            raise ValueError(f"distance_m must be a {g.rows}x{g.cols} float32 array")
        if bool(np.isnan(d).any()) or bool((d < 0).any()):
            raise ValueError("distance_m must hold non-negative distances or inf")
        return self


EpisodeStart.model_rebuild()


class MapUpdate(Message):
    kind: ClassVar[str] = "map_update"
    episode_id: str
    step: int = Field(ge=0)
    grid: GridSpec
    occupied: ZNDArray  # rows x cols bool
    free: ZNDArray  # rows x cols bool: free up to camera height and reachable from the robot
    explored: ZNDArray  # rows x cols bool
    values: dict[str, ZNDArray] = Field(default_factory=dict)  # semantic value layers, float32
    frontiers: list[Frontier] = Field(default_factory=list)
    prompt_points: list[PromptPoint] = Field(default_factory=list)
    pose: Pose2D
    explored_area_m2: float = 0.0
    timing_ms: dict[str, float] = Field(default_factory=dict)
    skill: SkillReport | None = None  # Frame.skill passed on (task episodes)
    objects: list[ObjectInstance] = Field(default_factory=list)  # HELIOS object layer (task episodes only)


MAX_MEMORY_VIEWS = 16  # joint answer: views in one prompt
MAX_MEMORY_VIEW_SIDE = 448  # pixels, the longer side of a memory view (the mapper downscales to this)


def _check_memory_views(views: list[np.ndarray]) -> list[np.ndarray]:
    for i, v in enumerate(views):
        if not isinstance(v, np.ndarray) or v.ndim != 3 or v.shape[2] != 3 or v.dtype != np.uint8:
            raise ValueError(f"memory view {i} must be an HxWx3 uint8 image")
        if min(v.shape[:2]) < 1 or max(v.shape[:2]) > MAX_MEMORY_VIEW_SIDE:
            raise ValueError(f"memory view {i} is {v.shape[1]}x{v.shape[0]} px: each side 1..{MAX_MEMORY_VIEW_SIDE}")
    return views


class PresenceQuery(BaseModel):
    """Two more yes/no prompts of a step (``services/vlm_scorer/prompts.py`` PRESENCE and IN_ROOM): is there an
    ``object`` in the image, and is the image taken in the ``room`` (None: not asked). What the closed-world
    existence rule (``services/stopper/closed_world.py``) and the room's extent read."""

    model_config = ConfigDict(extra="forbid")
    object: ClassName
    room: ClassName | None = None
    # False: only IN_ROOM is asked (counting across views needs the room, not the object; a prompt saved per step)
    ask_object: bool = True


class ScoreRequest(Message):
    """The four queries of one step (Explore-EQA Eq. 1, 2, 5 and the answer distribution), and the presence
    queries when ``presence`` names an object.

    Joint answer memory: with ``memory_views`` (1..16 images, each side <= 448 px) the request asks
    only for the answer distribution over ALL those views in one prompt (backends that take several images);
    the reply's ``relevance``/``lsv``/``gsv`` are then empty."""

    kind: ClassVar[str] = "score_request"
    request_id: str = Field(default_factory=lambda: new_id("req"))
    episode_id: str
    step: int = Field(ge=0)
    question: Question
    rgb: NDArray
    prompt_points: list[PromptPoint] = Field(default_factory=list)
    # Simulator ground truth of the frame, read only by the oracle backend.
    instances: NDArray | None = None
    labels: list[InstanceLabel] = Field(default_factory=list)
    depth: NDArray | None = None
    seed: int = 0
    memory_views: list[NDArray] = Field(default_factory=list, max_length=MAX_MEMORY_VIEWS)
    presence: PresenceQuery | None = None

    @field_validator("memory_views")
    @classmethod
    def _memory_views(cls, v: list[np.ndarray]) -> list[np.ndarray]:
        return _check_memory_views(v)


class ScoreResult(Message):
    kind: ClassVar[str] = "score_result"
    request_id: str
    episode_id: str
    step: int
    answer_probs: list[float]  # f(x^t) over the choices, sums to 1
    relevance: float  # Rel(x^t), Eq. 5
    lsv: list[float] = Field(default_factory=list)  # Eq. 1, one per prompt point
    gsv: float = 0.0  # Eq. 2
    backend: str
    model: str = ""
    replica: str = ""
    latency_ms: float = 0.0
    proposed_choices: list[str] = Field(default_factory=list)  # questions without choices (VI-A)
    # how the distribution was read: "logprobs" (the model's probabilities) or "sampling" (frequencies
    # of sampled completions, multiples of ``resolution`` = 1/valid samples); "" from older replicas
    mode: str = Field(default="", max_length=32)
    resolution: float = Field(default=0.0, ge=0.0, le=1.0)
    # P(Yes) to the presence prompts (None: not asked, PresenceQuery)
    object_yes: float | None = Field(default=None, ge=0.0, le=1.0)
    in_room: float | None = Field(default=None, ge=0.0, le=1.0)


class ErrorReply(Message):
    kind: ClassVar[str] = "error"
    source: str
    reason: str
    episode_id: str | None = None
    step: int | None = None
    request_id: str | None = None


MAX_EVIDENCE_INSTANCES = 64


class ObjectEvidence(BaseModel):
    """The HELIOS object layer's view of a question's target at one step: the Psi (HELIOS
    Eq. 7) of the target-class instances in the asked region, best first, and the observed share of that
    region. Combined with the VLM's answer by :mod:`services.stopper.object_evidence`."""

    model_config = ConfigDict(extra="forbid")
    category: Literal["counting", "existence"]
    psi: list[Annotated[float, Field(ge=0.0, le=1.0)]] = Field(default_factory=list,
                                                               max_length=MAX_EVIDENCE_INSTANCES)
    explored: float = Field(default=0.0, ge=0.0, le=1.0)


MAX_HOME_VIEWS = 256  # a home's view memory: keyframes kept (EQA_HOME_MAX_VIEWS is at most this)


class MemoryScore(BaseModel):
    """One remembered view of the episode's home re-scored for this question: a warm start's "memory step",
    decided on by the stopper before the robot's first move and kept in the episode's trace."""

    model_config = ConfigDict(extra="forbid")
    answer_probs: list[float] = Field(max_length=26)
    relevance: float
    view_step: int = Field(default=0, ge=0)  # the step of its own episode the view was taken at
    seen_at: float = 0.0  # when the view was taken (unix seconds)


class MemoryBounds(BaseModel):
    """What a warm start's memory steps and budget depend on (``EQA_HOME_*``): a conformal table calibrated on
    warm traces holds (Claim 1) for warm episodes run with the same bounds only, so traces and tables record
    them and the stopper warns on a mismatch (docs/homes.md, "The exchangeability assumption")."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    max_views: int = Field(ge=0, le=MAX_HOME_VIEWS)  # EQA_HOME_MAX_VIEWS
    warm_views: int = Field(ge=0, le=MAX_HOME_VIEWS)  # EQA_HOME_WARM_VIEWS
    memory_steps: int = Field(ge=0, le=MAX_HOME_VIEWS)  # EQA_HOME_MEMORY_STEPS
    warm_budget: float = Field(ge=0.0, le=1.0)  # EQA_HOME_WARM_BUDGET
    warm_area: Literal["explored", "observed"]  # EQA_HOME_WARM_AREA
    stale_weight: float = Field(ge=0.0, le=1.0)  # EQA_HOME_STALE_WEIGHT

    def differences(self, other: MemoryBounds) -> list[str]:
        """``name: mine vs other`` for every bound that differs."""
        return [f"{k} {v!r} vs {getattr(other, k)!r}" for k, v in self.model_dump().items() if getattr(other, k) != v]


class WarmStart(BaseModel):
    """A question that started from its home's memory (the home held a committed episode): the home's version
    it started from and the memory's bounds. The first question in an empty home has none: it is a cold one."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    version: int = Field(ge=1)
    bounds: MemoryBounds


class PresenceEvidence(BaseModel):
    """One step's signals of the closed-world existence rule (``services/stopper/closed_world.py``): P(Yes) to
    PRESENCE and IN_ROOM (None: no room asked) and the asked room's extent on the robot's map
    (``services/mapper/room_extent.py``)."""

    model_config = ConfigDict(extra="forbid")
    object_yes: float = Field(ge=0.0, le=1.0)
    in_room: float | None = Field(default=None, ge=0.0, le=1.0)
    room_area_m2: float = Field(ge=0.0, le=1e6)
    open_share: float = Field(ge=0.0, le=1.0)


class StepScores(Message):
    """What the stopper needs of one step: the answer distribution and the relevance."""

    kind: ClassVar[str] = "step_scores"
    episode_id: str
    step: int = Field(ge=0)
    answer_probs: list[float]
    relevance: float
    lsv: list[float] = Field(default_factory=list)
    gsv: float = 0.0
    backend: str = ""
    choices: list[str] = Field(default_factory=list)
    mode: str = Field(default="", max_length=32)  # the scorer's mode (ScoreResult.mode)
    object_evidence: ObjectEvidence | None = None  # the object layer's evidence (question episodes)
    presence: PresenceEvidence | None = None  # the closed-world rule's signals (EQA_CLOSED_WORLD)
    # joint answer memory: the steps whose views answer_probs was answered from in one prompt
    # (empty: answer_probs is this step's own view)
    answer_views: list[Annotated[int, Field(ge=0)]] = Field(default_factory=list, max_length=MAX_MEMORY_VIEWS)
    # warm start (a question in a known home, step 0 only): the home's remembered views re-scored for this
    # question, oldest first; the stopper takes them as steps before this one (services/stopper/state.py)
    memory: list[MemoryScore] = Field(default_factory=list, max_length=MAX_HOME_VIEWS)
    # warm start (step 0 only): the episode's step limit in a home whose map already covers part of the house
    # (eqa.budget.warm_step_limit); the stopper answers at it instead of at EpisodeStart.max_steps
    step_limit: StrictInt | None = Field(default=None, ge=1, le=10_000)
    # warm start (step 0 only): the episode started from its home's memory; the stopper then stops it on the
    # warm table (EQA_HOME_CALIBRATION_NAME) or says that its stopping is not calibrated for warm starts
    warm: WarmStart | None = None


class Decision(Message):
    kind: ClassVar[str] = "decision"
    episode_id: str
    step: int = Field(ge=0)
    rule: StopRule
    stop: bool
    reason: str
    prediction_set: list[str] = Field(default_factory=list)  # running intersection (CP)
    step_set: list[str] = Field(default_factory=list)  # C^t of this step (CP)
    scores: dict[str, float] = Field(default_factory=dict)  # rho^t_y (CP) or other rule's statistic
    answer: str | None = None
    q_hat: float | None = None
    # CP in a warm episode (StepScores.warm): True when q_hat is from a table calibrated on warm traces of the same
    # memory bounds, False when the stopping is not calibrated for this warm start (the reason says why); None:
    # a cold episode (or a cold table used as one)
    warm_calibrated: bool | None = None


class Goal(Message):
    """The planner's next pose, or the end of exploration (``done``) with its reason."""

    kind: ClassVar[str] = "goal"
    episode_id: str
    step: int = Field(ge=0)  # the step this goal follows; the sim renders step + 1 there
    pose: Pose2D | None = None
    path: list[tuple[float, float]] = Field(default_factory=list)
    frontier: Frontier | None = None
    weights: list[float] = Field(default_factory=list)
    done: bool = False
    reason: str = ""
    # task episodes: after moving to ``pose`` the sim runs ``skill`` on the planner's ``target``
    skill: Skill = "move"
    target: int | None = None  # object-layer instance id the skill aims at (the oracle pick uses ground truth)
    phase: TaskPhase | None = None
    # task episodes: the decision's numbers (Psi, Psi', IG, S, U, V, F, F0; NaN-free) for the task trace
    numbers: dict[Annotated[str, Field(max_length=16)], float] = Field(default_factory=dict, max_length=16)


class EpisodeEnd(Message):
    kind: ClassVar[str] = "episode_end"
    episode_id: str
    robot: str
    state: EpisodeState
    reason: str
    answer: str | None = None
    answer_text: str | None = None
    prediction_set: list[str] = Field(default_factory=list)
    steps: int = 0
    max_steps: int = 1
    correct: bool | None = None
    recording: str | None = None
    metrics: dict[str, float] = Field(default_factory=dict, max_length=32)  # task episodes: FindObj ... SR

    @property
    def normalized_steps(self) -> float:
        return self.steps / max(self.max_steps, 1)


class EpisodeStatus(BaseModel):
    """What the gateway reports about an episode (also the stored record)."""

    model_config = ConfigDict(extra="forbid")
    episode_id: str
    robot: str
    state: EpisodeState
    question: Question
    strategy: Strategy
    stop: StopConfig
    max_steps: int
    step: int = -1
    created_at: float = Field(default_factory=time.time)
    updated_at: float = Field(default_factory=time.time)
    answer: str | None = None
    answer_text: str | None = None
    prediction_set: list[str] = Field(default_factory=list)
    steps: int = 0
    normalized_steps: float = 0.0
    stop_reason: str | None = None
    correct: bool | None = None
    recording: str | None = None
    task: Task | None = None  # a task episode
    metrics: dict[str, float] = Field(default_factory=dict)  # its phase metrics (FindObj ... SR) at the end
    outcome: dict[str, Any] | None = None  # a finished task: success, first failure cause / phase, a line of text
    ablation: Ablation | None = None  # a task: the agent variant
    pick_limit: int | None = None  # a task: pick attempts (None = unlimited)


# ---- HELIOS object layer (docs/architecture.md) -----------------------------------------------------
MAX_DETECT_CLASSES = 32
MAX_DETECTIONS = 256
MAX_VALUE_TARGETS = 8
DetectClass = Annotated[str, Field(min_length=1, max_length=80)]


class Detection(BaseModel):
    """One detection of an open-vocabulary detector: class, confidence, box ``(x0, y0, x1, y1)`` (pixels,
    exclusive end) and the instance mask cropped to the box (``mask.shape == (y1 - y0, x1 - x0)``, bool)."""

    model_config = ConfigDict(arbitrary_types_allowed=True, extra="forbid")
    cls: str
    score: float = Field(ge=0.0, le=1.0)
    box: tuple[int, int, int, int]
    mask: NDArray

    @model_validator(mode="after")
    def _mask_fits_box(self) -> Detection:
        x0, y0, x1, y1 = self.box
        if not (0 <= x0 < x1 and 0 <= y0 < y1):
            raise ValueError(f"detection box {self.box} is empty or negative")
        if self.mask.shape != (y1 - y0, x1 - x0):
            raise ValueError(f"detection mask {self.mask.shape} does not match its box {self.box}")
        return self

    def full_mask(self, height: int, width: int) -> np.ndarray:
        """The mask pasted into a ``height x width`` image (clipped to it)."""
        out = np.zeros((height, width), dtype=bool)
        x0, y0, x1, y1 = self.box
        xa, ya, xb, yb = min(x0, width), min(y0, height), min(x1, width), min(y1, height)
        out[ya:yb, xa:xb] = np.asarray(self.mask, dtype=bool)[: yb - ya, : xb - xa]
        return out


class DetectRequest(Message):
    """Open-vocabulary detection of ``classes`` in one frame (HELIOS: DETIC with per-class thresholds
    od_a / od_g / od_b; ``thresholds`` parallel to ``classes``). Served by the scorer pool."""

    kind: ClassVar[str] = "detect_request"
    request_id: str = Field(default_factory=lambda: new_id("det"))
    episode_id: str
    step: int = Field(ge=0)
    rgb: NDArray
    classes: list[DetectClass] = Field(min_length=1, max_length=MAX_DETECT_CLASSES)
    thresholds: list[float] = Field(default_factory=list)
    # Simulator ground truth of the frame, read only by the oracle detector.
    instances: NDArray | None = None
    labels: list[InstanceLabel] = Field(default_factory=list)
    depth: NDArray | None = None
    seed: int = 0
    # With ``seed`` and ``step`` the key of a simulated model's draws (EpisodeStart.draws); None: the episode id.
    draws: str | None = Field(default=None, min_length=1, max_length=64, pattern=r"^[A-Za-z0-9_-]+$")

    @property
    def draw_key(self) -> str:
        return self.draws or self.episode_id

    @model_validator(mode="after")
    def _thresholds(self) -> DetectRequest:
        if self.thresholds and len(self.thresholds) != len(self.classes):
            raise ValueError(f"{len(self.thresholds)} thresholds for {len(self.classes)} classes: one per class")
        if any(not (0.0 <= t <= 1.0) for t in self.thresholds):
            raise ValueError("detection thresholds must be in [0, 1]")
        return self


class DetectResult(Message):
    kind: ClassVar[str] = "detect_result"
    request_id: str
    episode_id: str
    step: int
    detections: list[Detection] = Field(default_factory=list, max_length=MAX_DETECTIONS)
    backend: str
    model: str = ""
    replica: str = ""
    latency_ms: float = 0.0


class ValueRequest(Message):
    """The per-target value-layer prompt of HELIOS 3.1.2, "Seems like there is a (object) ahead", for each of
    ``targets`` on one image. Served by the scorer pool."""

    kind: ClassVar[str] = "value_request"
    request_id: str = Field(default_factory=lambda: new_id("val"))
    episode_id: str
    step: int = Field(ge=0)
    rgb: NDArray
    targets: list[DetectClass] = Field(min_length=1, max_length=MAX_VALUE_TARGETS)
    instances: NDArray | None = None
    labels: list[InstanceLabel] = Field(default_factory=list)
    depth: NDArray | None = None
    seed: int = 0
    # With ``seed`` and ``step`` the key of a simulated model's draws (EpisodeStart.draws); None: the episode id.
    draws: str | None = Field(default=None, min_length=1, max_length=64, pattern=r"^[A-Za-z0-9_-]+$")

    @property
    def draw_key(self) -> str:
        return self.draws or self.episode_id


class ValueResult(Message):
    kind: ClassVar[str] = "value_result"
    request_id: str
    episode_id: str
    step: int
    values: list[float]  # one per target, in [0, 1]
    backend: str
    model: str = ""
    replica: str = ""
    latency_ms: float = 0.0


class GazePoint(BaseModel):
    """A pose to look at an instance from, scored with Psi' (Eq. 11) and the optimistic IG (Eq. 12)."""

    model_config = ConfigDict(extra="forbid")
    x: float
    y: float
    yaw: float
    pitch: float
    psi_prime: float
    ig: float


class ObjectInstance(BaseModel):
    """One instance of the object layer (HELIOS 3.1.3): class = mode of argmax over its Gaussians; S, U, psi
    = S_c, U_c, Psi_c (Eq. 7) of that class; ``scores`` the same per task class; ``ig`` the best optimistic IG
    (Eq. 12) over ``gaze`` for the instance's believed task class."""

    model_config = ConfigDict(extra="forbid")
    instance_id: int
    cls: str
    S: float
    U: float
    psi: float
    scores: dict[str, tuple[float, float, float]] = Field(default_factory=dict)
    centre: tuple[float, float, float]
    extent: tuple[float, float, float]
    n_gaussians: int
    ig: float = 0.0
    gaze: list[GazePoint] = Field(default_factory=list)


MESSAGE_TYPES: dict[str, type[Message]] = {
    cls.kind: cls
    for cls in (
        EpisodeStart,
        EpisodeCancel,
        Frame,
        MapUpdate,
        ScoreRequest,
        ScoreResult,
        ErrorReply,
        StepScores,
        Decision,
        Goal,
        EpisodeEnd,
        DetectRequest,
        DetectResult,
        ValueRequest,
        ValueResult,
    )
}

STREAM_TYPES: dict[tuple[str, str], tuple[type[Message], ...]] = {
    keys.EPISODE_START: (EpisodeStart,),
    keys.EPISODE_CANCEL: (EpisodeCancel,),
    keys.EPISODE_END: (EpisodeEnd,),
    keys.SIM_FRAME: (Frame,),
    keys.SIM_ERROR: (ErrorReply,),
    keys.MAPPER_MAP: (MapUpdate,),
    keys.MAPPER_SCORES: (StepScores,),
    keys.MAPPER_ERROR: (ErrorReply,),
    keys.STOPPER_DECISION: (Decision,),
    keys.PLANNER_GOAL: (Goal,),
}

M = TypeVar("M", bound=Message)


def encode(msg: Message) -> bytes:
    """Message -> bytes (msgpack map with ``kind`` and the fields; arrays as raw bytes)."""
    body = msg.model_dump(mode="python")
    body["kind"] = msg.kind
    return packb(body)


def decode(payload: bytes, expected: type[M] | tuple[type[M], ...] | None = None) -> M:
    """Bytes -> message, checked against ``expected``. Raises :class:`CodecError` with the reason."""
    body = unpackb(payload)
    if not isinstance(body, dict):
        raise CodecError(f"payload is a {type(body).__name__}, expected a message map")
    kind = body.pop("kind", None)
    cls = MESSAGE_TYPES.get(kind) if isinstance(kind, str) else None
    if cls is None:
        raise CodecError(f"unknown message kind {kind!r}")
    version = body.get("schema_version", SCHEMA_VERSION)
    if not isinstance(version, int) or version > SCHEMA_VERSION:
        raise CodecError(f"{kind} has schema version {version!r}; this build understands <= {SCHEMA_VERSION}")
    if expected is not None:
        allowed = expected if isinstance(expected, tuple) else (expected,)
        if cls not in allowed:
            names = ", ".join(c.kind for c in allowed)
            raise CodecError(f"got a {kind} message where {names} was expected")
    try:
        return cls.model_validate(body)  # type: ignore[return-value]
    except ValidationError as exc:
        first = exc.errors()[0]
        where = ".".join(str(p) for p in first.get("loc", ()))
        raise CodecError(f"invalid {kind}: {where}: {first.get('msg')}") from exc


def model_json(model: BaseModel) -> dict[str, Any]:
    """JSON-safe dict of a model (arrays as dtype/shape/base64)."""
    return model.model_dump(mode="json")


class EpisodeLabel(BaseModel):
    """Ground truth given for a finished episode (``POST /v1/episodes/{id}/label``), stored under
    :func:`eqa.store.episode_label_key`; labelled full-length episodes are new calibration data."""

    model_config = ConfigDict(extra="forbid")
    schema_version: int = SCHEMA_VERSION
    episode_id: str = Field(min_length=1, max_length=64)
    answer: str = Field(min_length=1, max_length=1)  # the choice letter
    answer_text: str | None = Field(default=None, max_length=500)
    question_id: str | None = Field(default=None, max_length=200)
    tenant: str = Field(min_length=1, max_length=128)
    labelled_at: float = Field(default_factory=time.time)
