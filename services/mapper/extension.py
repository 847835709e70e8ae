"""Mapper extensions: the per-episode layers the mapper keeps beside its map, behind one small protocol.

:class:`services.mapper.service.MapperService` builds the map (TSDF, 2D maps, prompt points, the question's
semantic values, frontiers) and holds a list of :class:`MapperExtension` objects, each one plain object with its
own per-episode state, which it calls at fixed points of an episode and of each step:

=====================  =================================================================================
hook                   when, and what it may do
=====================  =================================================================================
``begin``              the episode's map is ready: a new episode (``restored`` False: set up its state, add
                       the value layers it writes) or one taken up from the store (its stored ``part``)
``observe``            a frame was integrated: work that must be done before any extension's requests go out
                       (the home's view memory re-scored at the first frame), outputs into :class:`StepOutputs`
``submit``             then: send its own scorer-pool requests (a future), answered while the mapper computes
                       the frontier candidates and waits for the step's scores
``score_request``      the step's :class:`~eqa.messages.ScoreRequest` is built: return it, changed or not
``scores``             the step's :class:`~eqa.messages.ScoreResult` came back (``again``: the frame of the last
                       step came again, nothing is fused twice): return it, changed or not; fill outputs
``apply``              the semantic values are written: fuse the answers of ``submit``, fill the step's
                       :class:`StepOutputs` (the frontiers' value layer, the object evidence)
``attach``             the step's :class:`~eqa.messages.MapUpdate` is built: add to it
``dump``               its part of the episode's stored state (``state_key``; None: no part)
``record``             the step is being recorded (rerun): log its own entities
``finish`` / ``close`` the episode ended (its map still whole) / the mapper stops
=====================  =================================================================================

Every hook has a default that does nothing, so an extension defines the ones it needs. The order of the
list is the order of the calls (``finish`` in reverse: an extension may use the state of one before it in the
list from its ``begin`` to its ``finish``) and of the parts in the stored state (a bare map header when no extension
stores anything, else ``{"map": header, <state_key>: part, ...}``, :func:`services.mapper.snapshots.with_state_part`),
so the stored bytes stay the same as long as the list does. An extension reaches the rest of the mapper only
through its :class:`MapperContext`: the settings, the scorer pool's calls, the error stream.

The four extensions: the HELIOS object layer of task episodes (:mod:`services.mapper.object_shell`), the
object evidence of question episodes (:mod:`services.mapper.question_objects`), the joint answer memory
(:mod:`services.mapper.answer_views`) and the home memory (:mod:`services.mapper.home_shell`: the episode's map
starts from its home's and is written back at the end; it reads the object layer's state, so it comes after it).

To add one: a class that subclasses :class:`MapperExtension` (explicitly, for the defaults) in its own module,
with a ``state_key`` no other extension uses and the hooks it needs, built from the
:class:`MapperContext` in :meth:`MapperService.__init__ <services.mapper.service.MapperService>` and appended
to ``extensions`` there. Appending keeps every existing stored state readable (its part is simply absent: the
``begin`` hook gets None); a stored part of an extension a mapper does not have is left aside on restore.
An output that goes into a message the mapper publishes gets a field in :class:`StepOutputs`.
"""

from __future__ import annotations

from collections.abc import Callable
from concurrent.futures import Future
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, ClassVar, Protocol

from eqa.bus import Bus
from eqa.messages import (
    DetectRequest,
    DetectResult,
    ErrorReply,
    Frame,
    MapUpdate,
    MemoryScore,
    ObjectEvidence,
    ScoreRequest,
    ScoreResult,
    ValueRequest,
    ValueResult,
    WarmStart,
)
from eqa.recording import EpisodeRecorder
from eqa.settings import SettingsGroup
from services.mapper.episode_map import EpisodeMap
from services.mapper.semantic_map import QUESTION_LAYER

if TYPE_CHECKING:
    from services.mapper.object_map import ObjectMapConfig

Scorer = Callable[[ScoreRequest], ScoreResult]
Detect = Callable[[DetectRequest], DetectResult]
Values = Callable[[ValueRequest], ValueResult]
ReportError = Callable[[str, str | None, int | None, str], None]  # (robot, episode id, step, reason)


TORCH_THREADS = 1  # torch intra-op threads of the mapper's object layer (see object_map_module)


def object_map_module() -> Any:
    """The object layer (torch) is imported on the first task episode, not when the mapper starts: question
    episodes never need it, and importing torch made every mapper (re)start several seconds slower -- longer than
    the sim's step resends wait for a restarted mapper.

    Torch then runs on :data:`TORCH_THREADS` thread: the mapper shares the cores with the other services, and
    torch's default (one thread per core, spinning while waiting) made the object layer 7-10x slower on the
    loaded 2-core machine (6 updates + 36 optimistic views: 1.3-1.4 s CPU with 1 thread, 10-12 s with 2),
    the same numbers either way."""
    import torch

    from services.mapper import object_map

    if torch.get_num_threads() != TORCH_THREADS:
        torch.set_num_threads(TORCH_THREADS)
    return object_map


def call_pool(call: Callable[[Any], Any], request: Any) -> Any:
    """The pool's answer to ``request``, or the exception the call raised: an extension's worker never raises,
    the caller reports the failure (:func:`failure`) and the step goes on without that answer."""
    try:
        return call(request)
    except Exception as exc:
        return exc


def failure(reply: Any) -> str:
    """Why ``reply`` (an :class:`~eqa.messages.ErrorReply` or an exception) is no answer."""
    return reply.reason if isinstance(reply, ErrorReply) else f"{type(reply).__name__}: {reply}"


class MapperContext:
    """What an extension may use of its mapper: the settings, the scorer pool's calls (``scorer``, ``detector``,
    ``values`` given in-process, else a :class:`~eqa.scorer_client.ScorerClient` on the bus, made when first
    needed), the object layer's configuration, and ``error`` (an :class:`~eqa.messages.ErrorReply` on the
    mapper's error stream)."""

    def __init__(self, settings: SettingsGroup, bus: Bus | None, error: ReportError, *, scorer: Scorer | None = None,
                 detector: Detect | None = None, values: Values | None = None) -> None:
        self.settings = settings
        self.bus = bus
        self.error = error
        self._scorer, self._detect, self._values = scorer, detector, values
        self._objects_config: ObjectMapConfig | None = None

    def score(self) -> Scorer:
        """The pool's ScoreRequest -> ScoreResult call."""
        if self._scorer is None:
            from eqa.scorer_client import ScorerClient  # imported when first needed

            self._scorer = ScorerClient(self.bus, self.settings).score
        return self._scorer

    def detect_and_values(self) -> tuple[Detect, Values]:
        """The pool's DetectRequest and ValueRequest calls (one client of their own)."""
        if self._detect is None or self._values is None:
            from eqa.scorer_client import ScorerClient

            client = ScorerClient(self.bus, self.settings)
            self._detect = self._detect or client.detect
            self._values = self._values or client.values
        return self._detect, self._values

    @property
    def objects_config(self) -> ObjectMapConfig:
        """The object layer's configuration (imports torch: only when an episode needs an object layer)."""
        if self._objects_config is None:
            self._objects_config = object_map_module().ObjectMapConfig.from_settings(self.settings)
        return self._objects_config


@dataclass
class StepOutputs:
    """What the extensions contribute to one step's published messages."""

    frontier_layer: str = QUESTION_LAYER  # the value layer the frontiers take their Eq. A6 values from
    object_evidence: ObjectEvidence | None = None  # StepScores.object_evidence
    answer_views: list[int] = field(default_factory=list)  # StepScores.answer_views
    memory: list[MemoryScore] = field(default_factory=list)  # StepScores.memory (the home's warm start)
    step_limit: int | None = None  # StepScores.step_limit (a question's budget in a known home)
    warm: WarmStart | None = None  # StepScores.warm (a question that started from its home's memory)


class MapperExtension(Protocol):
    """One extension of the mapper (module docstring); each hook's default does nothing."""

    state_key: ClassVar[str]  # its part of the episode's stored state

    def begin(self, episode_map: EpisodeMap, part: Any | None, restored: bool) -> None:
        """The episode's map is ready: a new episode (``restored`` False, ``part`` None; add the value layers it
        writes with :meth:`EpisodeMap.add_layer`) or one taken up from the store (``part``: its stored part, None
        when the state has none)."""

    def observe(self, robot: str, episode_map: EpisodeMap, frame: Frame, out: StepOutputs,
                timing: dict[str, float]) -> None:
        """The frame was integrated; runs before any extension's :meth:`submit`."""

    def submit(self, robot: str, episode_map: EpisodeMap, frame: Frame) -> Future[Any] | None:
        """Send the extension's own requests for the frame; their future goes to :meth:`apply`."""
        return None

    def score_request(self, episode_map: EpisodeMap, request: ScoreRequest) -> ScoreRequest:
        """The step's score request before it goes to the pool: return it, changed or not (e.g. with the presence
        prompts the extension needs)."""
        return request

    def scores(self, episode_map: EpisodeMap, frame: Frame, result: ScoreResult, out: StepOutputs,
               timing: dict[str, float], again: bool) -> ScoreResult:
        """The step's scores; ``again``: the last step's frame came again (fill ``out`` from the stored state,
        fuse nothing twice). Returns the scores, changed or not."""
        return result

    def apply(self, robot: str, episode_map: EpisodeMap, frame: Frame, pending: Future[Any] | None, out: StepOutputs,
              timing: dict[str, float]) -> None:
        """After the semantic values: fuse what :meth:`submit` asked for, fill ``out``."""

    def attach(self, episode_map: EpisodeMap, update: MapUpdate, frame: Frame) -> None:
        """Add to the step's map update."""

    def dump(self, episode_id: str) -> Any | None:
        """Its part of the episode's stored state; None: no part."""
        return None

    def record(self, episode_map: EpisodeMap, frame: Frame, recorder: EpisodeRecorder) -> None:
        """Log the step's own entities to the episode's (active) recorder."""

    def finish(self, episode_map: EpisodeMap) -> None:
        """The episode ended: drop its state (its map is still whole)."""

    def close(self) -> None:
        """The mapper stops: stop the extension's workers."""
