"""Tasks (HELIOS): submit "Move the <object> from the <start receptacle> to the <goal receptacle>" or
"Find a <object>" as an episode. Same lifecycle, auth, queueing, status, events and recording as questions:
the task episode is an :class:`eqa.messages.EpisodeStart` with ``task`` set and a stand-in question whose text
is the instruction (status and events at ``/v1/episodes/{id}``)."""

from __future__ import annotations

import functools
import logging
from typing import Annotated, Literal

from fastapi import APIRouter, status
from pydantic import BaseModel, ConfigDict, Field, StrictBool, ValidationError, field_validator
from starlette.concurrency import run_in_threadpool

from eqa.instructions import InstructionError, parse_instruction
from eqa.messages import SCENE_ID, Ablation, Pose2D, Task, TaskKind, check_text
from gateway.deps import ManagerDep, SettingsDep, SubmitterDep
from gateway.errors import InvalidError
from gateway.routers.episodes import errors
from gateway.schemas import HOME_DESCRIPTION, HomeName, QuestionRequest, Submitted, check_home, strict_pose

log = logging.getLogger(__name__)
router = APIRouter(prefix="/v1", tags=["tasks"])

_EXAMPLE = {"instruction": "Move the kettle from the kitchen counter to the coffee table", "scene": "gen-15000",
            "ablation": "helios", "pick_limit": 5}


class TaskRequest(BaseModel):
    """A task for one robot: the instruction in words (parsed here; 422 says which forms are understood), the
    scene and/or robot as for questions, the agent variant (Table 1: ``helios``, ``no_global``, ``trusting``) and
    the pick-attempt limit (1, 5, ... or none = unlimited)."""

    model_config = ConfigDict(extra="forbid", strict=True, json_schema_extra={"examples": [_EXAMPLE]})
    instruction: Annotated[str, Field(min_length=1, max_length=500)]
    kind: TaskKind | None = Field(default=None, description="pick_place or find_object; default: from the words")
    scene: Annotated[str, Field(min_length=1, max_length=64, pattern=f"^{SCENE_ID.pattern}$")] | None = None
    robot: Annotated[str, Field(min_length=1, max_length=64, pattern=r"^[A-Za-z0-9_-]+$")] | None = None
    start_pose: Pose2D | None = None
    ablation: Ablation = "helios"
    pick_limit: int | None = Field(default=None, ge=1, le=1000,
                                   description="pick attempts; default EQA_HELIOS_PICK_ATTEMPTS (0 = unlimited)")
    max_steps: int | None = Field(default=None, ge=1, le=10_000)
    seed: int = Field(default=0, ge=0, le=2**31 - 1, description="seed of the start pose sampling and the draws")
    draws: Annotated[str, Field(min_length=1, max_length=64, pattern=r"^[A-Za-z0-9_-]+$")] | None = Field(
        default=None, description="the key the simulated perception models draw from (with seed and step); default: "
        "the episode id, new for every episode. The same key, seed, task and start repeat a run step for step")
    record: StrictBool = True
    home: HomeName | None = Field(default=None, description=HOME_DESCRIPTION)

    @field_validator("start_pose", mode="before")
    @classmethod
    def _pose_numbers(cls, v: object) -> object:
        return strict_pose(v)

    @field_validator("home")
    @classmethod
    def _home(cls, v: str | None) -> str | None:
        return check_home(v)


def build_task(req: TaskRequest) -> Task:
    """The :class:`Task` of a request, or :class:`InvalidError` (422) saying what to write."""
    try:
        check_text(req.instruction, "instruction")
        parsed = parse_instruction(req.instruction)
    except (InstructionError, ValueError) as exc:
        raise InvalidError(str(exc), field="instruction") from exc
    if req.kind is not None and req.kind != parsed.kind:
        raise InvalidError(f"the instruction reads as a {parsed.kind} task, not {req.kind}", field="kind")
    kind: Literal["pick_place", "find_object"] = parsed.kind  # type: ignore[assignment]
    try:  # the Task checks what no parser can (the object named as its own receptacle, start = goal)
        return Task(kind=kind, text=req.instruction.strip(), scene=req.scene or "", object=parsed.object,
                    start_receptacle=parsed.start_receptacle, goal_receptacle=parsed.goal_receptacle,
                    start_pose=req.start_pose, max_steps=req.max_steps)
    except ValidationError as exc:
        msg = "; ".join(str(e.get("msg", "")).removeprefix("Value error, ") for e in exc.errors())
        raise InvalidError(msg, field="instruction") from exc


@router.post(
    "/tasks",
    response_model=Submitted,
    status_code=status.HTTP_202_ACCEPTED,
    summary="Submit a pick-and-place or find-object task; returns the episode id (running or queued)",
    responses=errors(400, 401, 403, 409, 413, 422, 429, 503),
)
async def submit_task(body: TaskRequest, manager: ManagerDep, caller: SubmitterDep, settings: SettingsDep
                      ) -> Submitted:
    manager.refuse_if_full(caller, body.robot)  # a full queue is refused on the event loop, at once
    task = build_task(body)
    limit = body.pick_limit if body.pick_limit is not None else (settings.helios_pick_attempts or None)
    stand_in = QuestionRequest(question=body.instruction.strip(), scene=body.scene, robot=body.robot,
                               start_pose=body.start_pose, stop_rule="max_steps", max_steps=body.max_steps,
                               seed=body.seed, record=body.record, home=body.home, question_id=body.draws)
    return await run_in_threadpool(
        functools.partial(manager.submit, stand_in, caller, task=task, ablation=body.ablation, pick_limit=limit,
                          draws=body.draws)
    )
