"""`cvqpg view` in a real browser (headless Chromium): refocusing with the slider, the arrow keys and the plane
marks, the linked zoom over both runs, and a screenshot."""

import importlib.util
from pathlib import Path

import pytest
from selenium.webdriver.common.action_chains import ActionChains
from selenium.webdriver.common.keys import Keys
from selenium.webdriver.support.ui import WebDriverWait

from cvqpg.cli import main
from cvqpg.view import write_view

_spec = importlib.util.spec_from_file_location(
    "view_screenshot", Path(__file__).resolve().parents[1] / "scripts" / "view_screenshot.py")
shots = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(shots)

pytestmark = [pytest.mark.slow, pytest.mark.skipif(
    not (shots.CHROMIUM and shots.CHROMEDRIVER),
    reason="no browser: needs Debian's chromium and chromium-driver (apt-get install chromium chromium-driver, "
           "as .ci/run does)")]

SMALL = ["--size", "64", "48", "--steps", "3", "--curvature-warmup", "1", "--quiet"]
# Frame 1 is the plane at 1 mm, frame 6 the plane at 5 mm; 8 frames in all.
DISTANCES = ["0.500 mm", "1.000 mm", "1.600 mm", "2.700 mm", "3.800 mm", "4.900 mm", "5.000 mm", "6.000 mm"]

ZOOM_MATCHES_FRAME = """
const done = arguments[arguments.length - 1];
Promise.all([...document.querySelectorAll("canvas.zoom")].map(async (zoom, run) => {
  const [x, y, w, h] = zoom.dataset.crop.split(",").map(Number);
  const image = new Image();
  image.src = data.runs[run].frames[Number(zoom.dataset.frame)];
  await image.decode();
  const expected = Object.assign(document.createElement("canvas"), { width: w, height: h }).getContext("2d");
  expected.drawImage(image, x, y, w, h, 0, 0, w, h);
  const shown = zoom.getContext("2d").getImageData(0, 0, zoom.width, zoom.height).data;
  const wanted = expected.getImageData(0, 0, w, h).data;
  return zoom.width === w && zoom.height === h && shown.every((v, i) => v === wanted[i]);
})).then(done);
"""


@pytest.fixture(scope="module")
def page(tmp_path_factory):
    root = tmp_path_factory.mktemp("browser")
    for name, options in (("cvqpg", []), ("flat", ["--primitive", "flat"])):
        assert main(["fit", *SMALL, *options, "--out", str(root / name)]) == 0
    return write_view([root / "cvqpg", root / "flat"], sweep=(0.5e-3, 6e-3, 6), progress=False).path


@pytest.fixture(scope="module")
def browser(page):
    with shots.chromium() as driver:
        shots.open_page(driver, page)
        yield driver


def shown(driver) -> tuple[str, list[bool]]:
    """The distance shown and, per run, whether its panel shows the frame of that distance."""
    return driver.execute_script("""
        const index = data.distances_mm.map((d) => `${d.toFixed(3)} mm`).indexOf(
            document.getElementById("distance").textContent);
        return [document.getElementById("distance").textContent,
                [...document.querySelectorAll("#view .frame img")].map(
                    (img, run) => img.src === data.runs[run].frames[index])];
    """)


FRAMES = "return [...document.querySelectorAll('#view .frame img')].map((i) => i.src)"  # each panel's image


def crops(driver) -> list[str]:
    return driver.execute_script("return [...document.querySelectorAll('canvas.zoom')].map((c) => c.dataset.crop)")


def test_slider_arrow_keys_and_plane_marks_refocus_both_runs(browser):
    assert shown(browser) == ["1.000 mm", [True, True]]  # it opens at the first training plane
    first = browser.execute_script(FRAMES)
    assert "PSNR" in browser.find_element("css selector", ".psnr").text
    browser.find_element("tag name", "body").send_keys(Keys.ARROW_RIGHT)
    assert shown(browser) == ["1.600 mm", [True, True]]
    assert browser.execute_script(FRAMES) != first
    assert browser.find_element("css selector", ".psnr").text == "no target at this distance"
    slider = browser.find_element("id", "slider")
    ActionChains(browser).move_to_element_with_offset(slider, slider.size["width"] // 2 - 2, 0).click().perform()
    assert shown(browser) == ["6.000 mm", [True, True]] and slider.get_attribute("value") == "7"
    marks = browser.find_elements("css selector", ".mark")
    assert [m.text for m in marks] == ["▲ 1 mm", "▲ 5 mm"]
    marks[1].click()
    assert shown(browser) == ["5.000 mm", [True, True]]


def test_the_zoom_crops_both_runs_alike(browser, tmp_path):
    frame, other = browser.find_elements("css selector", "#view .frame")
    assert crops(browser) == ["24,18,16,12"] * 2  # it opens on the central quarter
    shots.drag(browser, frame, (0.25, 0.25), (0.75, 0.75))
    WebDriverWait(browser, 10).until(lambda d: len(set(crops(d))) == 1 and crops(d)[0] != "24,18,16,12")
    x, y, w, h = map(int, crops(browser)[0].split(","))
    assert abs(x - 16) <= 1 and abs(y - 12) <= 1 and abs(w - 32) <= 1 and abs(h - 24) <= 1
    assert browser.execute_async_script(ZOOM_MATCHES_FRAME) == [True, True]
    shots.drag(browser, other, (0.9, 0.1), (0.9, 0.1))  # a click moves the crop, keeping its size
    WebDriverWait(browser, 10).until(lambda d: crops(d) == [f"{64 - w},0,{w},{h}"] * 2)
    assert browser.execute_async_script(ZOOM_MATCHES_FRAME) == [True, True]
    browser.find_element("tag name", "body").send_keys(Keys.ARROW_LEFT)  # the zoom follows the refocus
    WebDriverWait(browser, 10).until(lambda d: d.execute_script(
        "return [...document.querySelectorAll('canvas.zoom')].every((c) => c.dataset.frame === '5')"))
    assert browser.execute_async_script(ZOOM_MATCHES_FRAME) == [True, True]
    screenshot = tmp_path / "view.png"
    assert browser.save_screenshot(str(screenshot)) and screenshot.stat().st_size > 20_000
