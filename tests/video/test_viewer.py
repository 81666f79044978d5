"""`evhsi view`: the server's API, and the page in a real headless browser (Chromium
through Selenium: load, click a pixel, the plotted spectrum is the cube's)."""

import gc
import json
import shutil
import subprocess
import sys
import threading
import time
import urllib.error
import urllib.request
from pathlib import Path

import numpy as np
import pytest

import evhsi_jax as ev
from evhsi_jax._video._viewer import CubeSource, make_server

SCREENSHOTS = Path(__file__).resolve().parents[1] / "output"


@pytest.fixture(scope="module")
def cube_files(tmp_path_factory):
    d = tmp_path_factory.mktemp("view")
    rng = np.random.default_rng(4)
    wl = np.linspace(402.5, 757.5, 72)
    cube = rng.uniform(0.05, 0.9, (6, 9, 72)).astype(np.float32)
    truth = np.clip(cube + rng.normal(0, 0.02, cube.shape), 0, 1).astype(np.float32)
    ev.save_cube(d / "cube.npz", cube, wl)
    ev.save_cube(d / "truth.hdr", truth, wl)
    return d, cube, truth, wl


@pytest.fixture()
def server(cube_files):
    d, *_ = cube_files
    srv = make_server(CubeSource(d / "cube.npz", truth=d / "truth.hdr"), 0)
    thread = threading.Thread(target=srv.serve_forever, daemon=True)
    thread.start()
    yield f"http://127.0.0.1:{srv.server_address[1]}/"
    srv.shutdown()
    srv.server_close()


def _get(url):
    with urllib.request.urlopen(url, timeout=10) as r:
        return r.read()


def test_api_serves_meta_images_and_spectra(server, cube_files):
    _, cube, truth, wl = cube_files
    assert make_server.__doc__ and "127.0.0.1" in make_server.__doc__
    meta = json.loads(_get(server + "api/meta"))
    assert (meta["height"], meta["width"], meta["has_truth"]) == (6, 9, True)
    np.testing.assert_allclose(meta["wavelengths_nm"], wl)
    spec = json.loads(_get(server + "api/spectrum?x=4&y=2"))
    np.testing.assert_array_equal(np.float32(spec["spectrum"]), cube[2, 4])
    np.testing.assert_array_equal(np.float32(spec["truth"]), truth[2, 4])
    s, t = cube[2, 4].astype(float), truth[2, 4].astype(float)
    sam = np.degrees(np.arccos(s @ t / np.linalg.norm(s) / np.linalg.norm(t)))
    assert spec["sam_deg"] == pytest.approx(sam, abs=1e-6)
    assert _get(server + "api/image.png?channel=10")[:4] == b"\x89PNG"
    with pytest.raises(urllib.error.HTTPError) as err:
        _get(server + "api/spectrum?x=40&y=2")
    err.value.close()  # it holds the response open
    assert err.value.code == 400


def test_server_binds_only_to_loopback(cube_files):
    d, *_ = cube_files
    srv = make_server(CubeSource(d / "cube.npz"), 0)
    try:
        assert srv.server_address[0] == "127.0.0.1"
    finally:
        srv.server_close()


def test_cli_view_refuses_bad_input(cube_files, tmp_path):
    d, *_ = cube_files
    bad = tmp_path / "x.npz"
    bad.write_bytes(b"junk")
    for argv in (["view", str(bad)], ["view", str(d / "cube.npz"), "--port", "70000"]):
        r = subprocess.run([sys.executable, "-m", "evhsi_jax.cli", *argv],
                           capture_output=True, text=True, timeout=120)  # fmt: skip
        assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1, r.stderr


def _chrome():
    chromium = shutil.which("chromium") or shutil.which("chromium-browser")
    driver = shutil.which("chromedriver")
    if not chromium or not driver:
        pytest.skip(
            "no chromium/chromedriver on PATH: `make browser` installs Debian's "
            "chromium and chromium-driver"
        )
    webdriver = pytest.importorskip("selenium.webdriver")
    opts = webdriver.ChromeOptions()
    opts.binary_location = chromium
    for flag in ("--headless=new", "--no-sandbox", "--disable-gpu",
                 "--disable-dev-shm-usage", "--window-size=1200,800"):  # fmt: skip
        opts.add_argument(flag)
    service = webdriver.ChromeService(executable_path=driver)
    return webdriver.Chrome(options=opts, service=service)


def test_page_in_a_headless_browser(server, cube_files):
    _, cube, truth, _ = cube_files
    from selenium.webdriver.common.action_chains import ActionChains
    from selenium.webdriver.common.by import By
    from selenium.webdriver.support.ui import WebDriverWait

    browser = _chrome()
    try:
        browser.get(server)
        wait = WebDriverWait(browser, 20)
        canvas = browser.find_element(By.ID, "img")
        wait.until(lambda b: canvas.get_attribute("data-ready") == "1")
        scale = int(canvas.get_attribute("data-scale"))
        w, h = int(canvas.get_attribute("width")), int(canvas.get_attribute("height"))
        picks = [(4, 2), (7, 5)]
        for x, y in picks:  # click the middle of pixel (x, y), from the canvas centre
            ActionChains(browser).move_to_element_with_offset(
                canvas, int((x + 0.5) * scale - w / 2), int((y + 0.5) * scale - h / 2)
            ).click().perform()
            wait.until(lambda b, n=len(picks): len(b.find_elements(By.CSS_SELECTOR,
                       "polyline.spectrum")) >= 1)  # fmt: skip
            time.sleep(0.3)
        wait.until(lambda b: len(b.find_elements(By.CSS_SELECTOR, "polyline.spectrum")) == 2)
        lines = browser.find_elements(By.CSS_SELECTOR, "polyline.spectrum")
        truths = browser.find_elements(By.CSS_SELECTOR, "polyline.truth")
        for (x, y), line, tline in zip(picks, lines, truths):
            plotted = np.float32(json.loads(line.get_attribute("data-values")))
            np.testing.assert_array_equal(plotted, cube[y, x])
            np.testing.assert_array_equal(
                np.float32(json.loads(tline.get_attribute("data-values"))), truth[y, x]
            )
            assert len(line.get_attribute("points").split()) == cube.shape[-1]
        assert "SAM" in browser.find_element(By.ID, "pixels").text
        SCREENSHOTS.mkdir(exist_ok=True)
        browser.save_screenshot(str(SCREENSHOTS / "viewer.png"))
    finally:
        browser.quit()
    gc.collect()  # surface any socket left open here, not in a later test
