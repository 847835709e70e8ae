"""Rerun monitoring: one recording per episode, shared by every service.

Each service opens an :class:`EpisodeRecorder` for an episode; all use ``recording_id = episode_id`` and
``application_id = "eqa"``, so a viewer shows them as one recording. By default each service writes
``{data_dir}/recordings/{episode_id}/{service}.rrd`` (the gateway merges them with ``rerun rrd merge`` for
download: plain concatenation is not a valid rerun 0.41 file); with ``EQA_RERUN_URL`` set the data also
streams live to that viewer (``rerun+http://host:9876/proxy``) when the viewer accepts a connection at the
start of the episode; otherwise the episode is recorded to file only, with a warning (a gRPC sink to a dead
viewer holds every flush and disconnect for seconds: 17-22 s per episode were measured). Library code passes
the recorder's own ``RecordingStream`` (never the global one). The time line is ``step``
(``rr.set_time("step", sequence=t)``).

:data:`ENTITIES` names the entity path of each thing the design asks to see; services log under these
paths so that the merged recording of an episode is complete (the fleet test checks them).
"""

from __future__ import annotations

import logging
import os
import socket
import time
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

from eqa.settings import SettingsGroup

log = logging.getLogger(__name__)
APPLICATION_ID = "eqa"
TIMELINE = "step"

os.environ.setdefault("RERUN_TELEMETRY_ENABLED", "false")

# Entity paths of one episode, as the services log them (world frame: x/y horizontal, z up; 2D maps are
# images over the floor grid, row 0 = largest y). A layer or series below a path is allowed
# (``map/value/<layer>``, ``stopper/scores/<letter>``).
ENTITIES: dict[str, str] = {
    "rgb": "camera/rgb",  # sim: rr.Image of the frame
    "depth": "camera/depth",  # sim: rr.DepthImage (metres)
    "camera": "world/camera",  # sim: rr.Transform3D (camera-to-world) + rr.Pinhole
    "pose": "world/robot",  # sim: the base pose (rr.Arrows3D)
    "trajectory": "world/trajectory",  # sim: rr.LineStrips3D of the poses so far
    "occupancy": "map/occupancy",  # mapper: rr.Image of the occupied cells
    "explored": "map/explored",  # mapper: rr.Image of the explored cells
    "value": "map/value",  # mapper: one rr.Image per semantic value layer, map/value/<layer>
    "frontiers": "map/frontiers",  # mapper: rr.Points2D on the map, labels = Eq. A6 weights
    "frontier_weights": "world/frontiers",  # planner: rr.Points3D, radii/colours = sampling probabilities
    "prompt_points": "camera/prompt_points",  # mapper: rr.Points2D in pixels, labelled
    "goal": "world/plan/goal",  # planner: next pose; path under world/plan/path
    "prediction_set": "stopper/prediction_set",  # stopper: rr.TextLog of the set per step
    "scores": "stopper/scores",  # stopper: rr.Scalars per answer, stopper/scores/<letter>
    "task_phase": "task/phase",  # sim, task episodes: rr.TextLog per step (phase, skill, target, decision numbers)
    "task_flags": "task/metrics",  # sim, task episodes: rr.Scalars per step, task/metrics/<FindObj ... collisions>
    "task_outcome": "task/outcome",  # stopper, task episodes: rr.TextLog of the outcome (a failure at level WARN)
}

# What the design asks a demo episode's merged recording to hold (checked by the full-fleet test).
REQUIRED_ENTITIES = (
    "rgb",
    "depth",
    "pose",
    "trajectory",
    "occupancy",
    "explored",
    "value",
    "frontiers",
    "prompt_points",
    "prediction_set",
    "scores",
)


FLUSH_TIMEOUT_S = 10.0  # never wait longer than this for a recording to flush
VIEWER_CHECK_S = 0.3  # connect timeout of the viewer check
_viewer_checked: dict[str, tuple[float, bool]] = {}  # url -> (when, reachable), re-checked every 10 s


def recording_dir(settings: SettingsGroup, episode_id: str) -> Path:
    return settings.recordings_path / episode_id


def viewer_reachable(url: str) -> bool:
    """Whether a Rerun viewer accepts TCP connections at ``url`` (``rerun+http://host:port/proxy``); the
    answer is cached for 10 s per process. A warning is logged when it turns unreachable."""
    now = time.monotonic()
    seen = _viewer_checked.get(url)
    if seen is not None and now - seen[0] < 10.0:
        return seen[1]
    parts = urlsplit(url.removeprefix("rerun+"))
    try:
        with socket.create_connection((parts.hostname or "127.0.0.1", parts.port or 9876), timeout=VIEWER_CHECK_S):
            ok = True
    except OSError:
        ok = False
    if not ok and (seen is None or seen[1]):
        log.warning("Rerun viewer at %s is not reachable: recording to files only (EQA_RERUN_URL)", url)
    _viewer_checked[url] = (now, ok)
    return ok


class EpisodeRecorder:
    """A RecordingStream for one (episode, service); a no-op when recording is off.

    Never raises into service code: a failing log call is logged and dropped.
    """

    def __init__(self, settings: SettingsGroup, episode_id: str, service: str, enabled: bool = True) -> None:
        self.enabled = bool(enabled and settings.record)
        self.path: Path | None = None
        self.stream: Any = None
        self.live = False  # also streaming to the viewer at EQA_RERUN_URL
        if not self.enabled:
            return
        import rerun as rr

        self.stream = rr.RecordingStream(APPLICATION_ID, recording_id=episode_id, send_properties=False)
        out = recording_dir(settings, episode_id)
        out.mkdir(parents=True, exist_ok=True)
        self.path = out / f"{service}.rrd"
        sinks: list[Any] = [rr.FileSink(str(self.path))]
        self.live = bool(settings.rerun_url) and viewer_reachable(str(settings.rerun_url))
        if self.live:
            sinks.append(rr.GrpcSink(settings.rerun_url))
        self.stream.set_sinks(*sinks)

    def set_step(self, step: int) -> None:
        if self.stream is not None:
            self.stream.set_time(TIMELINE, sequence=int(step))

    def log(self, entity: str, archetype: Any, static: bool = False) -> None:
        if self.stream is None:
            return
        try:
            self.stream.log(entity, archetype, static=static)
        except Exception:
            log.exception("rerun log of %s failed", entity)

    def close(self) -> None:
        if self.stream is not None:
            try:
                self.stream.flush(timeout_sec=FLUSH_TIMEOUT_S)
                self.stream.disconnect()
            except Exception:
                log.debug("rerun close failed", exc_info=True)
            self.stream = None

    def __enter__(self) -> EpisodeRecorder:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
