"""Gateway episode manager, without HTTP: the order of what a client can observe when an episode ends."""

from __future__ import annotations

import json
import time

from eqa.bus import Bus
from eqa.messages import EpisodeEnd
from eqa.settings import Settings
from eqa.store import EmbeddedStore
from gateway.manager import EpisodeManager, ev_key
from gateway.schemas import QuestionRequest


def test_the_final_status_is_stored_before_the_end_event(settings: Settings, hub_settings: Settings, tmp_path) -> None:
    """A client that reads the episode_end event and then asks for the status must get the final status (a
    "running" status there makes `eqa ask` print "no answer" for an answered question)."""
    store = EmbeddedStore(tmp_path / "gw.sqlite")
    seen: list[tuple[str, str]] = []  # (kind of the last event, state stored at that moment)
    with Bus(hub_settings, "gateway", "test") as bus:
        manager = EpisodeManager(settings, store, bus)

        def notify() -> None:
            events = store.read(ev_key(episode_id), count=1000) if episode_id else []
            if events:
                kind = json.loads(events[-1][1])["kind"]
                episode = manager.load(episode_id)
                seen.append((kind, episode.status.state if episode else "?"))

        episode_id = ""
        manager.notify = notify
        sub = manager.submit(QuestionRequest(question="Is the oven on?", choices=["yes", "no"], robot="robot0",
                                             max_steps=5, record=False))
        episode_id = sub.episode_id
        manager.handle("robot0", EpisodeEnd(episode_id=episode_id, robot="robot0", state="stopped",
                                            reason="one answer left", answer="A", steps=2, max_steps=5))
    assert seen[-1] == ("episode_end", "stopped"), seen
    assert manager.load(episode_id).status.answer == "A"  # type: ignore[union-attr]


def test_the_watchdog_names_the_last_error(settings: Settings, hub_settings: Settings, tmp_path) -> None:
    """An episode stalled by a scorer that only answers errors fails with that error in its reason, not just
    "no message" (the services are all alive)."""
    from eqa.messages import ErrorReply

    store = EmbeddedStore(tmp_path / "gw.sqlite")
    with Bus(hub_settings, "gateway", "test") as bus:
        manager = EpisodeManager(settings.model_copy(update={"episode_timeout_s": 5.0}), store, bus)
        eid = manager.submit(QuestionRequest(question="Is the oven on?", choices=["yes", "no"], robot="robot0",
                                             max_steps=5, record=False)).episode_id
        why = "scorer failed: ScorerError: hf model directory '/x' does not exist (set EQA_HF_MODEL_PATH ...)"
        manager.handle("robot0", ErrorReply(source="mapper", episode_id=eid, step=0, reason=why))
        assert manager.check_timeouts(now=time.time() + 60) == [eid]
    st = manager.load(eid).status  # type: ignore[union-attr]
    assert st.state == "failed" and "no message for 5 s" in st.stop_reason
    assert f"last error: mapper at step 0: {why}" in st.stop_reason
