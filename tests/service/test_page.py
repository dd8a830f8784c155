"""The explorer page in a real browser: Playwright for Python driving the system's Chromium.

A real uvicorn serves the `tiny` checkpoint on a loopback port with the server's default limits (rate
limit included: the page must live within them). Every page records the responses that failed (4xx/5xx)
and its console errors. With NEMSIM_SCREENSHOTS=1 (the docs' screenshots, test_visit) it serves the
shipped small checkpoint instead, so the pictures show a trained model's etch. Skipped (with the
reason) when Playwright or a Chromium binary is missing; `.ci/run` installs Debian's `chromium`.
"""

from __future__ import annotations

import os
import shutil
import threading
import time
from pathlib import Path
from urllib.parse import urlparse

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
SHOWCASE = Path(__file__).resolve().parents[2] / "checkpoints" / "nemsim-small.pt"


@pytest.fixture(scope="module")
def server(tiny_checkpoint):
    showcase = os.environ.get("NEMSIM_SCREENSHOTS") == "1" and SHOWCASE.is_file()
    yield from _serve(SHOWCASE if showcase else tiny_checkpoint)


@pytest.fixture(scope="module")
def trench_server(tiny_section_checkpoint):
    yield from _serve(tiny_section_checkpoint)


def _serve(checkpoint):
    """A real uvicorn on a loopback port serving ``checkpoint`` with the default limits; yields its URL."""
    import uvicorn

    from service.config import Settings
    from service.main import create_app

    app = create_app(Settings(checkpoint=checkpoint, warmup_steps=1, runtime_backend="torch"))
    assert app.state.settings.rate_limit_per_minute > 0  # the default limits apply
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
    yield from _open(browser, server)


def _open(browser, base):
    """A fresh page of the explorer at ``base``, started, recording failed responses and console errors."""
    ctx = browser.new_context(viewport={"width": 1500, "height": 1000})
    pg = ctx.new_page()
    pg.console_errors, pg.failed, pg.requests = [], [], []
    pg.on("console", lambda m: m.type == "error" and pg.console_errors.append(m.text))
    pg.on("pageerror", lambda e: pg.console_errors.append(str(e)))
    pg.on("request", lambda r: pg.requests.append(r.url))
    pg.on(
        "response", lambda r: r.status >= 400 and pg.failed.append(f"{r.status} {r.request.method} {r.url}")
    )
    pg.on("requestfailed", lambda r: pg.failed.append(f"{r.failure} {r.method} {r.url}"))
    pg.goto(base + "/")
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


def drag_time_slider(page, to_left: bool, steps: int = 120) -> None:
    box = page.locator("#time").bounding_box()
    y, left, right = box["y"] + box["height"] / 2, box["x"] + 2, box["x"] + box["width"] - 2
    page.mouse.move(right if to_left else left, y)
    page.mouse.down()
    page.mouse.move(left if to_left else right, y, steps=steps)
    page.mouse.up()


def view3d_pixels(page) -> int:
    """Pixels of the 3-D view covered by surfaces (its nm rulers left out)."""
    return page.evaluate("() => window.explorer.surfacePixels()")


def test_page_runs_and_draws_without_console_errors(page):
    assert page.title() == "NEMSim process explorer"
    assert page.locator("#controls .ctl").count() == 14
    assert "nm" in page.inner_text("#controls") or "eV" in page.inner_text("#controls")
    set_control(page, "energy_mean_cl_plus", 400)
    run_and_wait(page)
    nchart, _ = canvas_stats(page, "#chart")
    assert view3d_pixels(page) > 1000, "the 3-D view is empty"
    assert nchart > 500, "the metrics chart is empty"
    assert page.locator("#final-metrics tr").count() >= 4
    assert page.is_hidden("#error")
    assert "ΔR: the change in Si removed" in page.inner_text("#mech-caption")  # the red bars explained
    page.wait_for_load_state("networkidle")
    assert sum("/mesh?" in url for url in page.requests) == 2  # the surfaces on screen, nothing more
    assert page.console_errors == []


def test_the_feature_is_set_drawn_sent_and_compared_a_b(page):
    """The geometry panel: the model's own feature prefilled (kinds it was not trained on disabled), a
    cross-section sketch, the note on the trained range; Run sends the feature (a 60 nm hole on the 40 nm
    model: the verdict is not trusted) and A/B rolls the same controls out on two features side by side."""
    assert [page.input_value(f"#geo-{k}") for k in ("kind", "cd", "mask")] == ["hole", "40", "80"]
    assert page.locator("#geo-kind option[value=trench]").is_disabled()
    assert canvas_stats(page, "#geo-sketch")[0] > 200, "the feature sketch is empty"
    assert "trained on holes of CD 40 nm, mask 80 nm" in page.inner_text("#geo-note")
    page.fill("#geo-cd", "60")
    assert "outside" in page.inner_text("#geo-note")
    run_and_wait(page)
    got = page.evaluate("() => [window.explorer.run.geometry, window.explorer.run.trust.level]")
    assert got == [{"kind": "hole", "cd_nm": 60.0, "mask_nm": 80.0}, "reject"]
    assert "level-reject" in page.get_attribute("#trust", "class")
    trust = page.inner_text("#trust")  # the feature decides, said first; never "inside the trained region"
    assert "never saw a hole of CD 60 nm" in trust and "extrapolation in geometry" in trust
    page.fill("#geo-b-cd", "48")
    page.click("#geo-ab-run")
    page.wait_for_selector("#geo-ab table", timeout=20_000)
    text = page.inner_text("#geo-ab")
    assert "A: hole 60/80 nm" in text and "B: hole 48/80 nm" in text and "etch_depth" in text
    page.wait_for_load_state("networkidle")
    assert page.console_errors == [] and page.failed == []


def test_a_trench_model_serves_its_trench(browser, trench_server):
    """A cross-section (trench) checkpoint: the page starts on its trench (holes disabled), runs it, draws the
    3-D view and the chart, and says the trained range, with no console errors or failed requests."""
    for pg in _open(browser, trench_server):
        assert [pg.input_value(f"#geo-{k}") for k in ("kind", "cd", "mask")] == ["trench", "40", "80"]
        assert pg.locator("#geo-kind option[value=hole]").is_disabled()
        assert "trained on trenches of" in pg.inner_text("#geo-note")
        assert "CD 32–48 nm" in pg.inner_text("#geo-note")
        run_and_wait(pg)
        assert pg.evaluate("() => window.explorer.run.geometry") == {"kind": "trench", "cd_nm": 40.0,
                                                                      "mask_nm": 80.0}
        assert view3d_pixels(pg) > 1000, "the 3-D view is empty"
        assert canvas_stats(pg, "#chart")[0] > 500, "the metrics chart is empty"
        pg.wait_for_load_state("networkidle")
        assert pg.console_errors == [] and pg.failed == []


def test_time_slider_changes_the_view(page):
    run_and_wait(page)
    _, before3d = canvas_stats(page, "#canvas3d")
    _, before_sec = canvas_stats(page, "#section")
    page.evaluate(
        "() => { const s = document.getElementById('time'); s.value = 0;"
        " s.dispatchEvent(new Event('input')); }"
    )
    page.wait_for_function("() => window.explorer.step === 0 && window.explorer.meshReady(0)")
    assert page.inner_text("#time-label").startswith("t = 0.0 s")
    assert canvas_stats(page, "#section")[1] != before_sec
    assert canvas_stats(page, "#canvas3d")[1] != before3d


def test_out_of_range_control_is_explained_in_plain_words(page):
    set_control(page, "energy_mean_ar_plus", 700)  # physically fine, outside the training range
    run_and_wait(page)
    assert page.is_visible("#warnings")
    text = page.inner_text("#warnings")
    assert "Outside the trained range" in text
    assert "energy_mean_ar_plus = 700 eV: above the trained range" in text
    assert "extrapolation" in text and "Verify with simulator" in text
    assert "no measured error outside the range" in text  # the tiny checkpoint records none there
    assert "field RMSE 0.500" in text  # ... and one test error, {"avg_rmse": 0.5} (conftest)
    assert "out" in page.get_attribute(".ctl[data-name='energy_mean_ar_plus']", "class")


def test_undefined_metrics_are_gaps(page):
    """The API's null (a width the hole has not reached the row of) is a gap on the page: "–" in the table,
    never 0.0, at the initial state."""
    run_and_wait(page)
    metrics = page.evaluate("() => window.explorer.run.metrics")
    assert all(metrics[n][0] is None for n in ("top_width", "neck_width", "bottom_width", "bowing"))
    page.evaluate("() => window.explorer.setStep(0)")
    cells = dict(row.split("\t")[:2] for row in page.inner_text("#final-metrics table").split("\n")[1:])
    assert cells["top_width"] == cells["bottom_width"] == cells["neck_depth"] == "–"
    assert cells["etch_depth"] == "0.0"


def test_plot_helpers_give_round_ticks_nm_frames_and_outlines(page):
    got = page.evaluate(
        """async () => {
          const p = await import('/static/plot.js');
          const ring = p.contour(Float32Array.from([1, 1, 1, 1, -1, 1, 1, 1, 1]), 3, 3);
          const f = p.planeFrame(window.explorer.model.scene);
          return { wide: p.niceTicks(0, 47.3).ticks, inside: p.ticksWithin(-52, 52, 4).ticks,
                   fine: p.niceTicks(0, 0.034).ticks,
                   bars: [p.scaleBarNm(47), p.scaleBarNm(9), p.scaleBarNm(100)],
                   ring, axis: [f.x(1 + f.cx), f.d(20.5), f.dlim, f.xlim] };
        }"""
    )
    assert got["wide"] == [0, 10, 20, 30, 40, 50]
    assert got["inside"] == [-50, 0, 50]  # within the axis limits (equal-aspect planes)
    assert got["fine"] == pytest.approx([0, 0.01, 0.02, 0.03, 0.04])
    assert got["bars"] == [20, 5, 100]
    ring = got["ring"]  # one material voxel: four segments joining the midpoints around it
    assert len(ring) == 16
    points = {(ring[k], ring[k + 1]) for k in range(0, 16, 2)}
    assert points == {(1, 0.5), (0.5, 1), (1.5, 1), (1, 1.5)}
    # tiny: 13 x 33 voxels of 8 nm, Si top at 20: x = 0 on the axis, depth 0 at the initial Si top
    assert got["axis"] == [0, 0, [-104, 160], [-52, 52]]


def test_design_asks_for_a_target_before_sending_anything(page):
    page.click("#tab-design-btn")
    assert page.locator("#design-targets input").count() == 10  # value and tolerance of 5 metrics
    assert page.get_attribute("#t-etch_depth", "placeholder") == "0–160"  # the Si thickness of tiny
    page.click("#design-run")
    assert "give at least one target" in page.inner_text("#design-status")
    assert not any(url.endswith("/design") for url in page.requests)


def test_bad_request_shows_a_readable_message_and_greys_the_old_results(page):
    run_and_wait(page)
    set_control(page, "energy_std_cl_plus", -5)
    page.click("#run")
    page.wait_for_selector("#error:not([hidden])", timeout=10_000)
    text = page.inner_text("#error")
    assert "energy_std_cl_plus" in text and "physically impossible" in text
    assert "greyed results are those of the previous Run" in text
    look = """() => ['trust', 'centre', 'right'].map((id) => {
      const s = getComputedStyle(document.getElementById(id)); return [+s.opacity, s.filter]; })"""
    assert all(opacity < 0.5 and "grayscale" in f for opacity, f in page.evaluate(look))  # verdict included
    page.click("#reset")
    run_and_wait(page, runs=2)
    assert page.is_hidden("#error")
    assert all(opacity == 1 and f == "none" for opacity, f in page.evaluate(look))


def test_a_simulator_job_can_be_cancelled_from_the_page(page):
    run_and_wait(page)
    page.click("#verify")
    page.wait_for_selector("#job-cancel:not([hidden])", timeout=10_000)
    page.click("#job-cancel")
    page.wait_for_function(
        "() => document.getElementById('job-status').textContent.endsWith('cancelled')", timeout=15_000
    )
    assert page.is_hidden("#error") and page.inner_text("#comparison") == ""


def test_a_busy_server_is_waited_out_not_drawn_empty(page):
    """A 429/503 is retried after its Retry-After (a run, and every mesh), never recorded as no surface."""
    asked: dict[str, list[float]] = {}

    def busy_once(route, status: int) -> None:
        times = asked.setdefault(f"{route.request.method} {route.request.url}", [])
        times.append(time.monotonic())
        if len(times) > 1:
            route.continue_()
            return
        body = '{"detail": "busy", "message": "busy: retry in 1 s"}'
        route.fulfill(status=status, headers={"Retry-After": "1"}, content_type="application/json", body=body)

    page.route("**/rollout", lambda route: busy_once(route, 503))
    page.route("**/rollouts/*/mesh?*", lambda route: busy_once(route, 429))
    run_and_wait(page)
    assert page.is_hidden("#error")
    assert view3d_pixels(page) > 1000, "the 3-D view is empty"
    assert page.evaluate("() => window.explorer.meshStats()") == {"requests": 4, "ok": 2}
    assert len(asked) == 3 and all(len(t) == 2 and t[1] - t[0] >= 0.95 for t in asked.values())


def test_after_run_the_results_are_in_view_at_1280x720(page):
    """With a warning and the trust verdict beside the controls, Run leaves the 3-D view, the cross-section
    and the metrics chart wholly on screen at 1280x720, unscrolled; a recipe's table sits above the
    controls, and the first control stays in view below the verdict and the warnings."""
    page.set_viewport_size({"width": 1280, "height": 720})
    set_control(page, "energy_mean_ar_plus", 700)  # outside the trained range: a warning and a verdict
    page.evaluate("() => window.scrollTo(0, 0)")  # as loaded (filling the control may have scrolled)
    run_and_wait(page)
    assert page.is_visible("#warnings") and page.is_visible("#trust")
    got = page.evaluate(
        """() => ({ scrolled: window.scrollY, boxes: Object.fromEntries(
          ['canvas3d', 'section', 'chart', 'controls'].map((id) => {
            const r = document.getElementById(id).getBoundingClientRect();
            return [id, [r.left, r.top, r.right, r.bottom]]; })) })"""
    )
    assert got["scrolled"] == 0
    boxes = got["boxes"]
    for name in ("canvas3d", "section", "chart"):
        left, top, right, bottom = boxes[name]
        assert 0 <= left and right <= 1280 and 0 <= top and bottom <= 720, (name, boxes[name])
        assert bottom - top >= 150 and right - left >= 150, (name, boxes[name])  # shown, not squeezed
    first = page.locator("#controls .ctl").first.bounding_box()
    assert first is not None and first["y"] + first["height"] <= 720
    page.check("#recipe-mode")
    recipe, controls = (page.locator(sel).bounding_box() for sel in ("#recipe", "#controls"))
    assert recipe["y"] + recipe["height"] <= controls["y"]


def test_the_3d_view_places_the_meshes_frame_in_its_box(page):
    """Meshes come with x, y from the hole axis and z above the initial Si top; the view moves them into
    its box (corner at the origin), so the initial Si top lies at si_top voxels up and the surface spans the
    box, half a padding voxel beyond each face."""
    run_and_wait(page)
    page.evaluate("() => window.explorer.setStep(0)")
    page.wait_for_function("() => window.explorer.meshReady(0)")
    got = page.evaluate(
        """async () => {
          const THREE = await import('/static/vendor/three/three.module.min.js');
          const b = new THREE.Box3().setFromObject(window.explorer.view.si), s = window.explorer.model.scene;
          return { min: b.min.toArray(), max: b.max.toArray(), scene: [s.nx, s.ny, s.si_top, s.voxel_nm] };
        }"""
    )
    nx, ny, si_top, v = got["scene"]
    assert got["min"][:2] == pytest.approx([-v / 2, -v / 2], abs=1e-3)
    assert got["max"] == pytest.approx([(nx + 0.5) * v, (ny + 0.5) * v, si_top * v], abs=1e-3)


def test_the_page_fits_1280x720_to_1920x1080(page):
    run_and_wait(page)
    page.wait_for_function("() => window.explorer.mechanisms && window.explorer.fit.mech !== undefined")
    for width, height in ((1280, 720), (1920, 1080)):
        page.set_viewport_size({"width": width, "height": height})
        page.wait_for_timeout(300)  # redrawn at the new size
        fit = page.evaluate(
            """() => ({
              scroll: document.documentElement.scrollWidth, inner: window.innerWidth,
              cut: [...document.querySelectorAll('canvas')].filter((c) => !c.hidden).filter((c) => {
                const r = c.getBoundingClientRect(), p = c.closest('section').getBoundingClientRect();
                return r.right > p.right + 0.5 || r.left < p.left - 0.5; }).map((c) => c.id),
              drawn: window.explorer.fit })"""
        )
        assert fit["scroll"] <= fit["inner"], f"{width}x{height}: {fit['scroll']} px wide"
        assert fit["cut"] == [], f"{width}x{height}: canvases wider than their panel"
        drawn = fit["drawn"]
        assert set(drawn) == {"chart", "mech", "profile"}, drawn
        assert all(drawn.values()), f"{width}x{height}: a legend or bars cut: {drawn}"
    assert page.console_errors == []


def test_docs_render_with_the_network_off(browser, server):
    ctx = browser.new_context()
    remote: list[str] = []

    def loopback_only(route) -> None:
        if urlparse(route.request.url).hostname in ("127.0.0.1", "localhost", "::1"):
            route.continue_()
        else:
            remote.append(route.request.url)
            route.abort()

    ctx.route("**/*", loopback_only)
    pg = ctx.new_page()
    try:
        pg.goto(server + "/docs")
        pg.wait_for_selector(".opblock", timeout=15_000)
        assert pg.locator(".opblock").count() >= 10
        assert "/rollout" in pg.inner_text(".swagger-ui")
        assert remote == []
    finally:
        ctx.close()
