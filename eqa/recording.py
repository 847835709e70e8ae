"""Rerun monitoring: one recording per episode, shared by every service.

Each service opens an :class:`EpisodeRecorder` for an episode; all use ``recording_id = episode_id`` and
``application_id = "eqa"``, so a viewer shows them as one recording. By default each service writes
``{data_dir}/recordings/{episode_id}/{service}.rrd`` (the gateway merges them for download); with
``EQA_RERUN_URL`` set the data also streams live to that viewer. Library code passes the recorder's own
``RecordingStream`` (never the global one).
"""

from __future__ import annotations

import logging
import os
from pathlib import Path
from typing import Any

from eqa.settings import Settings

log = logging.getLogger(__name__)
APPLICATION_ID = "eqa"

os.environ.setdefault("RERUN_TELEMETRY_ENABLED", "false")


def recording_dir(settings: Settings, episode_id: str) -> Path:
    return settings.recordings_path / episode_id


class EpisodeRecorder:
    """A RecordingStream for one (episode, service); a no-op when recording is off."""

    def __init__(self, settings: Settings, episode_id: str, service: str, enabled: bool = True) -> None:
        self.enabled = bool(enabled and settings.record)
        self.path: Path | None = None
        self.stream: Any = None
        if not self.enabled:
            return
        import rerun as rr

        self.stream = rr.RecordingStream(APPLICATION_ID, recording_id=episode_id, send_properties=False)
        out = recording_dir(settings, episode_id)
        out.mkdir(parents=True, exist_ok=True)
        self.path = out / f"{service}.rrd"
        sinks: list[Any] = [rr.FileSink(str(self.path))]
        if settings.rerun_url:
            sinks.append(rr.GrpcSink(settings.rerun_url))
        self.stream.set_sinks(*sinks)

    def set_step(self, step: int) -> None:
        if self.stream is not None:
            self.stream.set_time("step", sequence=int(step))

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
                self.stream.flush()
                self.stream.disconnect()
            except Exception:
                log.debug("rerun close failed", exc_info=True)
            self.stream = None
