"""Headless Chromium for the browser tests (the API docs pages and the web console).

The browser is Debian's ``chromium`` driven by Selenium through Debian's ``chromedriver`` (both installed by
``scripts/setup.sh``; Selenium never downloads a driver or a browser here). Every profile is fresh, and with
``offline=True`` the browser resolves no host but 127.0.0.1: a page that needs anything from the internet
(a CDN script, a web font) fails to show it, as it would on a machine without internet access.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

CHROMIUM = "/usr/bin/chromium"
CHROMEDRIVER = "/usr/bin/chromedriver"
OFFLINE_RULES = "MAP * ~NOTFOUND, EXCLUDE 127.0.0.1"
# Selenium Manager (run by Selenium to locate the browser) posts usage statistics to an analytics host and may
# look for downloads; no test reaches outside the machine.
SELENIUM_MANAGER_ENV = {"SE_AVOID_STATS": "true", "SE_OFFLINE": "true"}


def _require() -> None:
    for exe in (CHROMIUM, CHROMEDRIVER):
        if shutil.which(exe) is None:
            pytest.fail(f"{exe} is missing: run `make test` (scripts/setup.sh installs chromium chromium-driver)")


@contextlib.contextmanager
def chromium(profile_dir: Path, offline: bool = True, width: int = 1280, height: int = 900) -> Iterator[Any]:
    """A headless Chromium (a Selenium ``WebDriver``) with a fresh profile in ``profile_dir``; quit on exit."""
    _require()
    os.environ.update(SELENIUM_MANAGER_ENV)
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    opts = webdriver.ChromeOptions()
    opts.binary_location = CHROMIUM
    for arg in (
        "--headless=new",
        "--no-sandbox",
        "--disable-gpu",
        "--disable-dev-shm-usage",
        "--disable-quic",
        "--no-first-run",
        "--no-default-browser-check",
        "--disable-background-networking",
        "--disable-component-update",
        "--disable-sync",
        "--disable-extensions",
        "--disable-features=Translate,OptimizationHints,MediaRouter",
        f"--user-data-dir={profile_dir}",
        f"--window-size={width},{height}",
    ):
        opts.add_argument(arg)
    if offline:
        opts.add_argument(f"--host-resolver-rules={OFFLINE_RULES}")
    opts.set_capability("goog:loggingPrefs", {"browser": "ALL"})
    profile_dir.mkdir(parents=True, exist_ok=True)
    driver = webdriver.Chrome(options=opts, service=Service(executable_path=CHROMEDRIVER))
    try:
        driver.set_page_load_timeout(30)
        yield driver
    finally:
        driver.quit()


@contextlib.contextmanager
def fresh_page(driver: Any) -> Iterator[Any]:
    """The same browser for another test, in a new tab (so an empty sessionStorage: no token, no episode
    events kept by an earlier test), with no extra headers and no cookies."""
    old = driver.current_window_handle
    driver.switch_to.new_window("tab")
    new = driver.current_window_handle
    driver.switch_to.window(old)
    driver.close()
    driver.switch_to.window(new)
    driver.delete_all_cookies()
    driver.get_log("browser")  # drop what earlier tests logged
    yield driver


def send_header(driver: Any, name: str, value: str) -> None:
    """Send ``name: value`` with every request of this browser (DevTools ``Network.setExtraHTTPHeaders``)."""
    driver.execute_cdp_cmd("Network.enable", {})
    driver.execute_cdp_cmd("Network.setExtraHTTPHeaders", {"headers": {name: value}})


def wait_until(pred: Callable[[], Any], timeout: float = 20.0, every: float = 0.1, what: str = "") -> Any:
    """Poll ``pred`` (exceptions count as false) until it returns something true; fail with ``what``."""
    deadline = time.monotonic() + timeout
    last: BaseException | None = None
    while time.monotonic() < deadline:
        try:
            got = pred()
            if got:
                return got
        except Exception as exc:  # a stale element, a page still loading
            last = exc
        time.sleep(every)
    hint = f" (last: {last})" if last else ""
    raise AssertionError(f"timed out after {timeout} s waiting for {what or pred}{hint}")


def body_text(driver: Any) -> str:
    return driver.execute_script("return document.body ? document.body.innerText : ''") or ""
