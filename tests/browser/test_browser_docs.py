"""The API documentation pages render in a real browser with no internet access.

Headless Chromium (``support.browser``) resolves no host but 127.0.0.1, so a page whose script or style
comes from a CDN stays blank. A check for "200 OK" cannot see that; these tests wait for the page's
scripts and read what a person would see: the operations of the API (the POST of questions) and no
"Unable to render this definition" (what Swagger UI 3.x/4.x says about FastAPI's OpenAPI 3.1 document).
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from support.browser import body_text, chromium, fresh_page, send_header, wait_until
from support.fleet import GatewayThread, lone_gateway_settings
from support.gateway import TOKEN

SHOTS = os.environ.get("EQA_SCREENSHOTS")  # a directory: save what the browser showed (docs/usage.md pictures)


@pytest.fixture(scope="module")
def docs_gateway(tmp_path_factory: pytest.TempPathFactory) -> Iterator[GatewayThread]:
    """A gateway with a token and no fleet (the docs need none), on its own Zenoh port and store."""
    s = lone_gateway_settings(tmp_path_factory.mktemp("docs-gw") / "var", [TOKEN])
    with GatewayThread(s) as gw:
        yield gw


@pytest.fixture(scope="module")
def browser(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Any]:
    with chromium(tmp_path_factory.mktemp("chromium") / "profile") as b:
        yield b


def _failed_loads(driver: object) -> list[str]:
    """Requests the browser could not complete (a CDN it cannot reach shows up here)."""
    return [e["message"] for e in driver.get_log("browser") if e.get("source") == "network"]  # type: ignore[attr-defined]


def _shot(driver: object, name: str) -> None:
    if SHOTS:
        Path(SHOTS).mkdir(parents=True, exist_ok=True)
        driver.save_screenshot(str(Path(SHOTS) / name))  # type: ignore[attr-defined]


def test_swagger_ui_lists_the_operations_offline(browser: Any, docs_gateway: GatewayThread) -> None:
    with fresh_page(browser) as b:
        send_header(b, "Authorization", f"Bearer {TOKEN}")
        b.get(f"{docs_gateway.url}/docs")
        wait_until(
            lambda: (
                b.find_elements("css selector", ".opblock-post .opblock-summary-path")
                or "Unable to render" in body_text(b)
            ),
            timeout=30,
            what="Swagger UI to render the spec",
        )
        text = body_text(b)
        assert "Unable to render" not in text, text[:500]
        paths = {
            e.text.replace("\u200b", "") for e in b.find_elements("css selector", ".opblock-post .opblock-summary-path")
        }
        assert "/v1/questions" in paths, paths
        assert "/v1/episodes/{episode_id}/events" in text.replace("\u200b", "")
        assert "GET" in text and "DELETE" in text
        assert _failed_loads(b) == []
        _shot(b, "docs.png")


def test_redoc_lists_the_operations_offline(browser: Any, docs_gateway: GatewayThread) -> None:
    with fresh_page(browser) as b:
        send_header(b, "Authorization", f"Bearer {TOKEN}")
        b.get(f"{docs_gateway.url}/redoc")
        wait_until(lambda: "Submit a question" in body_text(b), timeout=30, what="ReDoc to list the operations")
        text = body_text(b)
        assert "Unable to render" not in text and "Something went wrong" not in text, text[:500]
        # The operation's method and path as ReDoc shows them in its right-hand panel.
        ops = b.execute_script(
            "return Array.from(document.querySelectorAll('button span')).map(e => e.textContent.trim())"
        )
        assert "post" in [o.lower() for o in ops] and "/v1/questions" in text, ops[:20]
        assert _failed_loads(b) == []
        b.execute_script(
            "const h = Array.from(document.querySelectorAll('h2')).find(e => e.textContent.startsWith('Submit'));"
            "h.scrollIntoView();"
        )
        _shot(b, "redoc.png")


def _status(b: Any) -> int | None:
    """The HTTP status of the page the browser shows (Navigation Timing)."""
    return b.execute_script("const n = performance.getEntriesByType('navigation')[0]; return n && n.responseStatus")


def test_docs_pages_still_need_the_token(browser: Any, docs_gateway: GatewayThread) -> None:
    with fresh_page(browser) as b:
        for page in ("/docs", "/redoc"):
            b.get(f"http://anyone:wrong-token@127.0.0.1:{docs_gateway.port}{page}")
            assert wait_until(lambda: _status(b), what="the page's status") == 401
            assert "/v1/questions" not in body_text(b)


def test_a_person_can_type_the_token_into_the_browser_prompt(browser: Any, docs_gateway: GatewayThread) -> None:
    """With tokens set, /docs answers 401 with one challenge per line, so the browser asks for a password and
    keeps it for the site. Here the password comes with the address (Chromium sends it only when challenged with
    Basic) and goes into the browser's credential cache, as from the prompt; then the plain address renders,
    the spec fetched with the cached password. Before, the challenge was one line ('Bearer, Basic realm=...'),
    Chromium asked for nothing and the page stayed a 401."""
    with fresh_page(browser) as b:
        b.get(f"http://anyone:{TOKEN}@127.0.0.1:{docs_gateway.port}/docs")
        assert wait_until(lambda: _status(b), what="the page's status") == 200
        for page in ("/docs", "/redoc"):
            b.get(f"{docs_gateway.url}{page}")
            wait_until(
                lambda: "/v1/questions" in body_text(b).replace("\u200b", "") or _status(b) == 401,
                timeout=30,
                what=f"{page} with the remembered password",
            )
            assert _status(b) == 200 and "Unable to render" not in body_text(b)
