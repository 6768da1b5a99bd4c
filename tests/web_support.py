"""A real browser for the web page's tests: Debian's `chromium`, headless, driven by Selenium through Debian's
`chromium-driver` (both installed by `make system-deps`).

Why Selenium with chromium-driver rather than Playwright for Python:
- Debian builds chromedriver from the same source package as chromium and apt upgrades the two together, so
  the driver always speaks the installed browser's exact version. Playwright drives Chromium over the
  DevTools protocol at the revision its own release was built against; Debian's chromium moves with every
  security update (150 to 156 within bookworm) and can run ahead of it.
- Nothing downloads at run time: the driver's path is given, so Selenium Manager (which can fetch drivers
  and browsers) is never asked, and `no_downloads` makes any call to it fail the test. Playwright's wheel
  carries its own Node.js runtime and expects `playwright install` to download browser builds.
- WebDriver's `get_cookies` returns HttpOnly cookies too, so a test can check the session cookie's flags
  and reuse it for plain-HTTP refusal checks.

Chromium runs with --no-sandbox (CI runs as root in a container, where its sandbox cannot start) and a
profile in the test's temporary folder. Without chromium and chromedriver the browser tests are skipped,
except under CI (or QUEKARO_REQUIRE_CHROMIUM=1), where they fail: CI must not pass by skipping them.
"""

from __future__ import annotations

import os
import time
import urllib.error
import urllib.request
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
from selenium import webdriver
from selenium.webdriver.chrome.service import Service
from selenium.webdriver.common import selenium_manager
from selenium.webdriver.common.by import By
from selenium.webdriver.remote.webdriver import WebDriver

from farm.local import LocalFarm

CHROMIUM = Path("/usr/bin/chromium")
CHROMEDRIVER = Path("/usr/bin/chromedriver")
WINDOW = (1400, 1000)


def missing_browser() -> str | None:
    """Why the browser cannot run here, or None."""
    for path, package in ((CHROMIUM, "chromium"), (CHROMEDRIVER, "chromium-driver")):
        if not (path.is_file() and os.access(path, os.X_OK)):
            return f"{path} not found: apt-get install {package} (make system-deps installs it)"
    return None


def require_browser() -> None:
    """Skip without chromium, or fail where the browser tests must run (CI)."""
    reason = missing_browser()
    if reason is None:
        return
    if os.environ.get("CI") or os.environ.get("QUEKARO_REQUIRE_CHROMIUM"):
        pytest.fail(reason)
    pytest.skip(reason)


def no_downloads(monkeypatch: pytest.MonkeyPatch) -> None:
    """Fail if Selenium ever asks Selenium Manager for a driver or a browser (it may download them)."""
    def refuse(*_args: Any, **_kwargs: Any) -> Any:
        raise AssertionError("Selenium Manager was asked for a driver or browser: nothing may download")

    monkeypatch.setattr(selenium_manager.SeleniumManager, "binary_paths", refuse)


def start_browser(profile: Path) -> WebDriver:
    """Headless Debian chromium through Debian's chromedriver, its profile in `profile`."""
    options = webdriver.ChromeOptions()
    options.binary_location = str(CHROMIUM)
    for arg in ("--headless=new", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage",
                "--no-first-run", "--disable-extensions", "--disable-background-networking",
                f"--window-size={WINDOW[0]},{WINDOW[1]}", f"--user-data-dir={profile}"):
        options.add_argument(arg)
    profile.mkdir(parents=True, exist_ok=True)
    service = Service(executable_path=str(CHROMEDRIVER), log_output=str(profile / "chromedriver.log"))
    driver = webdriver.Chrome(service=service, options=options)
    driver.set_page_load_timeout(60)
    return driver


def screenshot(driver: WebDriver, folder: Path, name: str) -> Path:
    """A PNG of the window under `folder` (the test's temporary folder)."""
    path = folder / f"{name}.png"
    assert driver.save_screenshot(str(path)), f"no screenshot {path}"
    return path


def wait_until(check: Callable[[], Any], timeout: float, what: str, every: float = 0.25) -> Any:
    """`check()`'s first truthy value within `timeout` s (exceptions count as not yet)."""
    deadline = time.monotonic() + timeout
    last: Exception | None = None
    while time.monotonic() < deadline:
        try:
            value = check()
            if value:
                return value
        except Exception as exc:  # an element not there yet, a stale one
            last = exc
        time.sleep(every)
    raise AssertionError(f"timed out after {timeout:.0f} s waiting for {what} (last error: {last})")


def click(driver: WebDriver, css: str, timeout: float = 20) -> None:
    """Click the element `css` selects, again if the page replaced it meanwhile (its tables are redrawn
    on every event: an element found a moment ago may be stale)."""
    wait_until(lambda: driver.find_element(By.CSS_SELECTOR, css).click() is None, timeout, f"a click on {css}")


def rows(driver: WebDriver, css: str) -> list[dict[str, Any]]:
    """The rows `css` selects, read at one instant by the page itself: each its data-*, its child elements'
    texts (a table row's cells) and its whole text."""
    return driver.execute_script(
        "return [...document.querySelectorAll(arguments[0])].map((r) => "
        "({data: {...r.dataset}, cells: [...r.children].map((c) => c.textContent), text: r.textContent}));", css)


class _NoRedirect(urllib.request.HTTPRedirectHandler):
    def redirect_request(self, *args: Any, **kwargs: Any) -> None:
        return None


def http(method: str, url: str, headers: dict[str, str] | None = None,
         data: bytes | None = None) -> tuple[int, dict[str, str], bytes]:
    """(status, headers, body) of one plain request, redirects not followed, errors as answers."""
    request = urllib.request.Request(url, data=data, method=method, headers=headers or {})
    opener = urllib.request.build_opener(_NoRedirect)
    try:
        with opener.open(request, timeout=30) as response:
            return response.status, dict(response.headers), response.read()
    except urllib.error.HTTPError as exc:
        return exc.code, dict(exc.headers), exc.read()



def module_farm(tmp_path_factory: pytest.TempPathFactory) -> Iterator[LocalFarm]:
    """A browser test module's farm (`farm = pytest.fixture(scope="module", name="farm")(module_farm)`): the
    embedded XMPP server, the master and two render agents of one Dr.Jit thread each."""
    require_browser()
    with LocalFarm(tmp_path_factory.mktemp("farm"), agents=2, threads=1) as farm:
        farm.wait_for_agents()
        yield farm


def module_browser(farm: LocalFarm, tmp_path_factory: pytest.TempPathFactory) -> Iterator[WebDriver]:
    """A browser test module's chromium (after its farm), with nothing allowed to download."""
    with pytest.MonkeyPatch.context() as patch:
        no_downloads(patch)
        driver = start_browser(tmp_path_factory.mktemp("chromium-profile"))
        try:
            yield driver
        finally:
            driver.quit()
