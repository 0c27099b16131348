"""Shared fixtures: the real service as a subprocess, and the shared datasets directory.

Kept generic on purpose: only what several test files need. The process helpers themselves live in
tests/service_process.py (`ServiceProcess`, `RobotProcess`, `free_port`, `wait_for`).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

import pytest
from service_process import DATASETS_DIR, ServiceProcess


@pytest.fixture(scope="session", autouse=True)
def compiled_kernels() -> None:
    """Compile the engine's kernels (or load them from numba's cache) once, before any test.

    A fresh clone has no cache, and the first integration compiles for about 10 s on the CI
    machine. Tests that time integration (queue and timeout tests, in-process APIs) would otherwise
    absorb that compile in whichever runs first. Service subprocesses load what this writes."""
    from fleetmap.warm_up import warm_up

    warm_up()


@pytest.fixture
def service_factory(tmp_path: Path) -> Iterator[Callable[..., ServiceProcess]]:
    """Start services with extra `fleetmap serve` arguments: `service_factory("--no-auto-create")`.
    Every service started is stopped (SIGTERM, then kill) at teardown."""
    started: list[ServiceProcess] = []

    def start(*extra_args: str, args: Sequence[str] = ()) -> ServiceProcess:
        svc = ServiceProcess(tmp_path, [*extra_args, *args])
        started.append(svc)
        return svc.start()

    yield start
    for svc in started:
        svc.stop()


@pytest.fixture
def service(service_factory: Callable[..., ServiceProcess]) -> ServiceProcess:
    """A running service with default options on free ports (`base_url`, `zenoh_endpoint`)."""
    return service_factory()


@pytest.fixture(scope="session")
def datasets_dir() -> Path:
    """../shared/datasets next to the repository; the test is skipped (visibly) when it is absent."""
    if not DATASETS_DIR.is_dir():
        pytest.skip(f"shared datasets not found at {DATASETS_DIR}")
    return DATASETS_DIR


@pytest.fixture(scope="module")
def browser() -> Iterator[Any]:
    """One headless Chromium (Debian's, see test_web_viewer.py) for a module of viewer tests."""
    from playwright.sync_api import sync_playwright
    from test_web_viewer import CHROMIUM, CHROMIUM_ARGS

    with sync_playwright() as pw:
        b = pw.chromium.launch(executable_path=str(CHROMIUM), args=CHROMIUM_ARGS)
        try:
            yield b
        finally:
            b.close()


#: Records, in `window.cspViolations`, what the page's Content-Security-Policy blocked (the
#: `securitypolicyviolation` events); added before any of the page's own scripts runs.
CSP_RECORDER_JS = """
window.cspViolations = [];
document.addEventListener('securitypolicyviolation', (e) => {
  window.cspViolations.push(`${e.effectiveDirective} blocked ${e.blockedURI || '(inline)'}`);
});
"""


def is_csp_report(text: str) -> bool:
    """Whether a console message is Chromium's report of something a Content-Security-Policy blocked."""
    return "Content Security Policy" in text


@pytest.fixture
def page(browser: Any) -> Iterator[Any]:
    """A 1280 x 800 page of the module's browser, closed after the test; `page.page_errors` collects
    the page's uncaught JavaScript errors, `page.csp_reports` what the service's Content-Security-
    Policy blocked (Chromium's console reports). A test fails if the policy blocked anything: the
    viewer would be broken in a way its own checks may not see."""
    p = browser.new_page(viewport={"width": 1280, "height": 800})
    p.page_errors = []
    p.csp_reports = []
    p.on("pageerror", lambda e: p.page_errors.append(str(e)))
    p.on("console", lambda m: p.csp_reports.append(m.text) if is_csp_report(m.text) else None)
    p.add_init_script(CSP_RECORDER_JS)
    try:
        yield p
        blocked = p.csp_reports
        assert blocked == [], f"the Content-Security-Policy blocked what the viewer needs: {blocked}"
    finally:
        p.close()
