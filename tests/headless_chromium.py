"""Open a local HTML page in Debian's headless Chromium (selenium + the matching chromedriver).

Skips the calling test with a clear message when Chromium, chromedriver or selenium is missing
(`.ci/run` installs them with apt where it can).
"""

from __future__ import annotations

import shutil
import tempfile
from pathlib import Path

import pytest

CHROMIUM_FLAGS = ["--headless=new", "--no-sandbox", "--disable-gpu", "--no-first-run", "--disable-background-networking",
                  "--disable-component-update", "--disable-sync", "--enable-unsafe-swiftshader",
                  "--disable-dev-shm-usage", "--window-size=1400,3200"]


def chromium_or_skip():
    """A selenium Chrome driver on /usr/bin/chromium, or pytest.skip saying what is missing."""
    browser = shutil.which("chromium") or shutil.which("chromium-browser")
    driver_path = shutil.which("chromedriver")
    if not browser or not driver_path:
        pytest.skip("headless Chromium not installed (apt-get install -y chromium chromium-driver; .ci/run does it "
                    "where apt works): the flight review page was written but not opened in a browser")
    try:
        from selenium import webdriver
        from selenium.webdriver.chrome.service import Service
    except ImportError:
        pytest.skip("selenium not installed (pip install -e '.[test]'): the page was not opened in a browser")
    opts = webdriver.ChromeOptions()
    opts.binary_location = browser
    profile = tempfile.mkdtemp(prefix="uavsearch-chromium-")
    for flag in CHROMIUM_FLAGS + [f"--user-data-dir={profile}"]:
        opts.add_argument(flag)
    opts.set_capability("goog:loggingPrefs", {"browser": "ALL"})
    drv = webdriver.Chrome(service=Service(executable_path=driver_path), options=opts)
    drv.set_page_load_timeout(60)
    drv.set_script_timeout(60)
    drv._uavsearch_profile = profile
    return drv


def close(drv) -> None:
    try:
        drv.quit()
    finally:
        shutil.rmtree(getattr(drv, "_uavsearch_profile", ""), ignore_errors=True)


# Every plot's traces as plotly.js holds them after rendering (typed arrays decoded to plain lists).
PLOT_DATA_JS = """
const plain = a => (a === undefined || a === null) ? null : Array.from(a);
return Array.from(document.querySelectorAll('.js-plotly-plot')).map(gd => ({
  id: gd.id,
  traces: gd._fullData.map((t, i) => ({name: t.name, type: t.type, visible: t.visible,
                                  x: t.type === 'image' ? null : plain(t.x), y: t.type === 'image' ? null : plain(t.y),
                                  z: (t.type === 'heatmap' && t.z) ? Array.from(t.z).map(r => Array.from(r)) : null,
                                  source: t.type === 'image' ? (gd.data[i].source || '').length : null})),
  sliders: (gd.layout.sliders || []).map(s => s.steps.length),
  annotations: (gd.layout.annotations || []).map(a => a.text),
  svg_paths: gd.querySelectorAll('path').length,
}));
"""


def open_page(drv, page: Path, screenshot: Path) -> tuple[list, list]:
    """Load the page, wait for every plot to render; (severe console messages, plot data). Saves a screenshot."""
    from selenium.webdriver.support.ui import WebDriverWait

    drv.get(page.resolve().as_uri())
    WebDriverWait(drv, 60).until(lambda d: d.execute_script(
        "return document.readyState === 'complete' && document.querySelectorAll('.js-plotly-plot').length > 0 && "
        "Array.from(document.querySelectorAll('.js-plotly-plot')).every(g => g._fullLayout !== undefined)"))
    data = drv.execute_script(PLOT_DATA_JS)
    height = drv.execute_script("return document.body.scrollHeight")
    drv.set_window_size(1400, min(int(height) + 40, 6000))
    drv.save_screenshot(str(screenshot))
    logs = drv.get_log("browser")
    severe = [e["message"] for e in logs if e.get("level") == "SEVERE"]
    return severe, data
