"""The console's homes view in a real browser (headless Chromium, ``support.browser``) against the real gateway
over HTTP with a real Redis: the list, one home's summary and map picture, reset (refused while an episode of
the home runs, then done), the home field of the ask form, and another tenant's token seeing nothing.

No services run: an episode the gateway starts stays "running", which the refused reset needs. The home's
memory is written through the contract the mapper writes it with (:func:`eqa.homes.write_summary`,
:func:`eqa.homes.map_png_key`).
"""

from __future__ import annotations

import io
import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest
from PIL import Image
from support.browser import body_text, chromium, fresh_page, wait_until
from support.fleet import GatewayThread
from test_homes_api import SCENE, A, B, Q, _clear, _settings, _tenant

from eqa import homes
from eqa.store import open_store

SHOTS = os.environ.get("EQA_SCREENSHOTS")  # a directory: save the views (docs pictures)


def shot(b: Any, name: str) -> None:
    if SHOTS:
        Path(SHOTS).mkdir(parents=True, exist_ok=True)
        b.save_screenshot(str(Path(SHOTS) / name))


@pytest.fixture(scope="module")
def gw(tmp_path_factory: pytest.TempPathFactory, redis_url: str) -> Iterator[GatewayThread]:
    s = _settings(Path(tmp_path_factory.mktemp("homes-console")), redis_url)
    _clear(s)
    with GatewayThread(s) as g:
        yield g
    _clear(s)


@pytest.fixture(scope="module")
def browser(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Any]:
    with chromium(tmp_path_factory.mktemp("chromium") / "profile", height=1100) as b:
        yield b


def _as(b: Any, url: str, token: str) -> None:
    b.get(url + "/v1/health")
    b.execute_script("sessionStorage.setItem('eqa.token', arguments[0])", token)


def _map_png() -> tuple[bytes, tuple[int, int]]:
    img = np.zeros((90, 140, 3), np.uint8)
    img[10:80, 10:130] = (235, 235, 235)
    img[40:50, 60:80] = (200, 40, 40)
    buf = io.BytesIO()
    Image.fromarray(img).save(buf, format="PNG")
    return buf.getvalue(), (140, 90)


def _js(b: Any, script: str) -> Any:
    return b.execute_script(script)


def test_homes_view_summary_map_reset_and_tenants(browser: Any, gw: GatewayThread) -> None:
    with httpx.Client(base_url=gw.url, timeout=30) as c:
        run = c.post("/v1/questions", json={**Q, "home": "flat-1"}, headers=A)
        assert run.status_code == 202, run.text
        eid = run.json()["episode_id"]
        other = c.post("/v1/questions", json={**Q, "home": "flat-2"}, headers=A).json()["episode_id"]
        c.delete(f"/v1/episodes/{other}", headers=A)
        hid = homes.home_id(_tenant("tok-a"), "flat-1")
        png, (w, h) = _map_png()
        with open_store(gw.settings) as store:
            homes.write_summary(store, homes.HomeSummary(home=hid, episodes=2, views=12, bytes=3 * 1024 * 1024,
                                                         scenes=[SCENE]))
            store.set(homes.map_png_key(hid), png)

        with fresh_page(browser) as b:
            _as(b, gw.url, "tok-a")
            b.get(gw.url + "/#homes")
            rows = wait_until(lambda: b.find_elements("css selector", "#h-list tbody tr"), what="home rows")
            names = [r.get_attribute("data-home") for r in rows]
            assert names == ["flat-2", "flat-1"], names
            row = b.find_element("css selector", "#h-list tr[data-home=flat-1]")
            cells = [td.text for td in row.find_elements("tag name", "td")]
            assert cells[:4] == ["flat-1", "12", "3.0 MiB", "1"] and cells[5] == "1 running or queued", cells
            flat2 = [td.text for td in b.find_elements("css selector", "#h-list tr[data-home=flat-2] td")]
            assert flat2[1] == "none yet" and flat2[5] == "idle", flat2
            assert "2 homes of this token" in b.find_element("id", "h-count").text
            shot(b, "console-homes.png")

            # one home: summary, its running episode, the map picture as stored, the stored parts
            row.find_element("tag name", "a").click()
            wait_until(lambda: _js(b, "return location.hash") == "#homes/flat-1", what="the home's page")
            views = wait_until(lambda: b.find_element("css selector", "dd[data-term=views]").text, what="summary")
            assert views == "12"
            assert b.find_element("css selector", "dd[data-term=size]").text == "3.0 MiB"
            assert b.find_element("css selector", "dd[data-term=house]").text == SCENE
            assert b.find_element("css selector", "dd[data-term='episodes mapped']").text == "2"
            assert b.find_element("css selector", "dd[data-term=scenes]").text == SCENE
            assert [a.text for a in b.find_elements("css selector", "#h-active a")] == [eid]
            size = wait_until(lambda: _js(b, "const i = document.getElementById('h-map'); return i.complete && "
                                             "i.naturalWidth ? [i.naturalWidth, i.naturalHeight] : null"),
                              what="the map picture")
            assert tuple(size) == (w, h) and b.find_element("id", "h-map").is_displayed()
            assert b.find_element("id", "h-parts").text == "map.png, summary"
            shot(b, "console-home.png")

            # reset asks twice; refused (409) while its episode runs, and nothing is lost
            b.find_element("id", "h-reset").click()
            assert "Really reset flat-1" in b.find_element("id", "h-reset").text
            b.find_element("id", "h-reset").click()
            msg = wait_until(lambda: "not reset" in b.find_element("id", "h-reset-state").text
                             and b.find_element("id", "h-reset-state").text, what="the refused reset")
            assert "queued or running" in msg and eid in msg
            assert c.get("/v1/homes/flat-1", headers=A).json()["memory"]["views"] == 12

            # after its episode: reset, back to the list without it
            assert c.delete(f"/v1/episodes/{eid}", headers=A).json()["state"] == "cancelled"
            b.find_element("id", "h-reset").click()
            b.find_element("id", "h-reset").click()
            wait_until(lambda: "home flat-1 reset" in b.find_element("id", "h-count").text, what="the reset")
            assert _js(b, "return location.hash") == "#homes"
            names = [r.get_attribute("data-home") for r in b.find_elements("css selector", "#h-list tbody tr")]
            assert names == ["flat-2"]
            assert c.get("/v1/homes/flat-1", headers=A).status_code == 404
            with open_store(gw.settings) as store:
                assert store.keys(homes.prefix(hid)) == []

            # the ask form's home field names the home of the episode
            b.get(gw.url + "/#ask")
            b.find_element("id", "q-question").send_keys("Where is the black suitcase?")
            b.find_element("id", "q-scene").send_keys(SCENE)
            b.find_element("id", "q-max-steps").send_keys("3")
            b.find_element("id", "q-home").send_keys("flat-3")
            b.find_element("id", "ask-submit").click()
            wait_until(lambda: _js(b, "return location.hash").startswith("#watch/ep-"), what="the new episode")
            asked = _js(b, "return location.hash").split("/", 1)[1]
            assert c.get("/v1/homes/flat-3", headers=A).json()["active_episodes"] == [asked]
            c.delete(f"/v1/episodes/{asked}", headers=A)
            # ... and so does the task form's
            b.get(gw.url + "/#ask")
            b.find_element("id", "t-instruction").send_keys("Find a mug")
            b.find_element("id", "t-scene").send_keys(SCENE)
            b.find_element("id", "t-home").send_keys("flat-3")
            b.find_element("id", "task-submit").click()
            wait_until(lambda: _js(b, "return location.hash").startswith("#watch/ep-")
                       and _js(b, "return location.hash").split("/", 1)[1] != asked, what="the task episode")
            task = _js(b, "return location.hash").split("/", 1)[1]
            info = c.get("/v1/homes/flat-3", headers=A).json()
            assert info["active_episodes"] == [task] and info["episodes_submitted"] == 2
            c.delete(f"/v1/episodes/{task}", headers=A)

        # another tenant's token: no homes, and A's home by name is not found
        with fresh_page(browser) as b:
            _as(b, gw.url, "tok-b")
            b.get(gw.url + "/#homes")
            wait_until(lambda: "no homes yet" in b.find_element("id", "h-count").text, what="B's empty list")
            b.get(gw.url + "/#homes/flat-2")
            wait_until(lambda: "No home flat-2 of this token" in b.find_element("id", "h-name").text,
                       what="A's home hidden from B")
            assert "flat-1" not in body_text(b) and "12" not in b.find_element("id", "h-summary").text
            assert b.find_element("id", "h-map-fig").get_attribute("hidden") is not None
        assert c.get("/v1/homes/flat-2", headers=B).status_code == 404
