"""Gateway episode manager, without HTTP: the order of what a client can observe when an episode ends."""

from __future__ import annotations

import json

from eqa.bus import Bus
from eqa.messages import EpisodeEnd
from eqa.settings import Settings
from eqa.store import EmbeddedStore
from gateway.manager import EpisodeManager
from gateway.schemas import QuestionRequest


def test_the_final_status_is_stored_before_the_end_event(settings: Settings, hub_settings: Settings, tmp_path) -> None:
    """A client that reads the episode_end event and then asks for the status must get the final status (it
    used to see "running" now and then: `eqa ask` printed "no answer" for an answered question)."""
    store = EmbeddedStore(tmp_path / "gw.sqlite")
    seen: list[tuple[str, str]] = []  # (kind of the last event, state stored at that moment)
    with Bus(hub_settings, "gateway", "test") as bus:
        manager = EpisodeManager(settings, store, bus)

        def notify() -> None:
            events = store.read(f"gw:ev:{episode_id}", count=1000) if episode_id else []
            if events:
                kind = json.loads(events[-1][1])["kind"]
                rec = manager.load(episode_id)
                seen.append((kind, rec.status.state if rec else "?"))

        episode_id = ""
        manager.notify = notify
        sub = manager.submit(QuestionRequest(question="Is the oven on?", choices=["yes", "no"], robot="robot0",
                                             max_steps=5, record=False))
        episode_id = sub.episode_id
        manager.handle("robot0", EpisodeEnd(episode_id=episode_id, robot="robot0", state="stopped",
                                            reason="one answer left", answer="A", steps=2, max_steps=5))
    assert seen[-1] == ("episode_end", "stopped"), seen
    assert manager.load(episode_id).status.answer == "A"  # type: ignore[union-attr]
