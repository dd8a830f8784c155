"""The explorer page in a real browser: Playwright for Python driving the system's Chromium.

A real uvicorn serves the `tiny` checkpoint on a loopback port. Skipped (with the reason) when Playwright
or a Chromium binary is missing; `.ci/run` installs Debian's `chromium`.
"""

from __future__ import annotations

import os
import shutil
import threading
import time

import httpx
import pytest

from service.protocol import free_port

sync_api = pytest.importorskip(
    "playwright.sync_api", reason="playwright is not installed (pip install -e .[test])"
)

CHROMIUM = os.environ.get("NEMSIM_CHROMIUM") or shutil.which("chromium") or shutil.which("chromium-browser")
pytestmark = pytest.mark.skipif(
    CHROMIUM is None, reason="no Chromium found (apt-get install chromium, or set NEMSIM_CHROMIUM)"
)
ARGS = [
    "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
    "--disable-background-networking", "--disable-component-update", "--disable-sync",
]  # fmt: skip



@pytest.fixture(scope="module")
def server(tiny_checkpoint):
    import uvicorn

    from service.config import Settings
    from service.main import create_app

    app = create_app(
        Settings(checkpoint=tiny_checkpoint, warmup_steps=1, rate_limit_per_minute=0, runtime_backend="torch")
    )
    port = free_port()
    srv = uvicorn.Server(uvicorn.Config(app, host="127.0.0.1", port=port, log_level="warning"))
    thread = threading.Thread(target=srv.run, daemon=True)
    thread.start()
    base = f"http://127.0.0.1:{port}"
    deadline = time.monotonic() + 60
    while True:
        try:
            if httpx.get(f"{base}/ready", timeout=2).status_code == 200:
                break
        except httpx.TransportError:
            pass
        assert time.monotonic() < deadline, "server did not become ready"
        time.sleep(0.2)
    yield base
    srv.should_exit = True
    thread.join(10)


@pytest.fixture(scope="module")
def browser():
    with sync_api.sync_playwright() as pw:
        b = pw.chromium.launch(executable_path=CHROMIUM, args=ARGS, headless=True)
        yield b
        b.close()


@pytest.fixture
def page(browser, server):
    ctx = browser.new_context(viewport={"width": 1500, "height": 1000})
    pg = ctx.new_page()
    pg.console_errors = []
    pg.on("console", lambda m: m.type == "error" and pg.console_errors.append(m.text))
    pg.on("pageerror", lambda e: pg.console_errors.append(str(e)))
    pg.goto(server + "/")
    try:
        pg.wait_for_selector("body[data-ready='1']", state="attached", timeout=15_000)
    except sync_api.TimeoutError:
        pytest.fail(f"the page did not start; console: {pg.console_errors}")
    yield pg
    ctx.close()


def set_control(page, name: str, value: float) -> None:
    page.fill(f"#c-{name}", str(value))


def run_and_wait(page, runs: int = 1) -> None:
    page.click("#run")
    page.wait_for_selector(f"body[data-runs='{runs}']", state="attached", timeout=20_000)


def canvas_stats(page, selector: str) -> tuple[int, str]:
    """(pixels differing from the top-left background pixel, a hash of the pixels)."""
    return page.evaluate(
        """(sel) => {
          const c = document.querySelector(sel);
          const tmp = document.createElement('canvas'); tmp.width = c.width; tmp.height = c.height;
          const ctx = tmp.getContext('2d'); ctx.drawImage(c, 0, 0);
          const d = ctx.getImageData(0, 0, c.width, c.height).data;
          let n = 0, h = 0;
          for (let i = 0; i < d.length; i += 4) {
            if (Math.abs(d[i] - d[0]) + Math.abs(d[i + 1] - d[1]) + Math.abs(d[i + 2] - d[2]) > 12) n++;
            h = (h * 31 + d[i] + 3 * d[i + 1] + 7 * d[i + 2]) >>> 0;
          }
          return [n, String(h)];
        }""",
        selector,
    )


def test_page_runs_and_draws_without_console_errors(page):
    assert page.title() == "NEMSim process explorer"
    assert page.locator("#controls .ctl").count() == 14
    assert "nm" in page.inner_text("#controls") or "eV" in page.inner_text("#controls")
    set_control(page, "energy_mean_cl_plus", 400)
    run_and_wait(page)
    n3d, _ = canvas_stats(page, "#canvas3d")
    nchart, _ = canvas_stats(page, "#chart")
    assert n3d > 1000, "the 3-D view is empty"
    assert nchart > 500, "the metrics chart is empty"
    assert page.locator("#final-metrics tr").count() >= 4
    assert page.is_hidden("#error")
    page.wait_for_timeout(300)  # mesh prefetch and mechanisms in flight
    assert page.console_errors == []


def test_time_slider_changes_the_view(page):
    run_and_wait(page)
    _, before3d = canvas_stats(page, "#canvas3d")
    _, before_sec = canvas_stats(page, "#section")
    page.evaluate(
        "() => { const s = document.getElementById('time'); s.value = 0;"
        " s.dispatchEvent(new Event('input')); }"
    )
    page.wait_for_function("() => window.explorer.step === 0")
    page.wait_for_timeout(500)  # the step-0 meshes arrive
    assert page.inner_text("#time-label").startswith("t = 0.0 s")
    assert canvas_stats(page, "#section")[1] != before_sec
    assert canvas_stats(page, "#canvas3d")[1] != before3d


def test_out_of_range_control_shows_the_api_warning(page):
    set_control(page, "energy_mean_ar_plus", 700)  # physically fine, outside the training range
    run_and_wait(page)
    assert page.is_visible("#warnings")
    assert "energy_mean_ar_plus" in page.inner_text("#warnings")
    assert "out" in page.get_attribute(".ctl[data-name='energy_mean_ar_plus']", "class")


def test_bad_request_shows_a_readable_message(page):
    set_control(page, "energy_std_cl_plus", -5)
    page.click("#run")
    page.wait_for_selector("#error:not([hidden])", timeout=10_000)
    text = page.inner_text("#error")
    assert "energy_std_cl_plus" in text and "physically impossible" in text


def test_simulator_job_from_the_page_shows_the_comparison(page):
    run_and_wait(page)
    page.click("#pin-a")
    page.click("#verify")
    page.wait_for_selector("#comparison[data-done='1']", timeout=40_000)
    text = page.inner_text("#comparison")
    assert "avg RMSE" in text and "etch_depth" in text
    assert page.is_visible("#rmse") and canvas_stats(page, "#rmse")[0] > 100
    assert "simulator" in page.inner_text("#final-metrics")  # its curves join the chart and table


def test_ab_and_recipe_mode(page):
    run_and_wait(page)
    _, alone = canvas_stats(page, "#section")
    page.click("#pin-a")
    assert canvas_stats(page, "#section")[1] != alone  # A's cross-section beside the current one
    page.check("#recipe-mode")
    page.click("#add-phase")
    set_control(page, "energy_mean_cl_plus", 450)
    page.click("#add-phase")
    assert page.locator("#recipe-table tbody tr").count() == 2
    run_and_wait(page, runs=2)
    assert page.evaluate("() => window.explorer.run.recipe.length") == 50  # two phases of 2.5 s
    ab = page.inner_text("#ab")
    assert "energy_mean_cl_plus" in ab and "current − A" in ab
    assert page.console_errors == []


def test_a_simulator_job_can_be_cancelled_from_the_page(page):
    run_and_wait(page)
    page.click("#verify")
    page.wait_for_selector("#job-cancel:not([hidden])", timeout=10_000)
    page.click("#job-cancel")
    page.wait_for_function(
        "() => document.getElementById('job-status').textContent.endsWith('cancelled')", timeout=15_000
    )
    assert page.is_hidden("#error") and page.inner_text("#comparison") == ""
