"""Screenshot a `cvqpg view` page in headless Chromium, refocused and with a crop picked, as the README shows it.

    python scripts/view_screenshot.py runs/demo/view_vs_demo-flat.html docs/view.png --index 1 --crop 0.3 0.35 0.55 0.6

Needs Debian's `chromium` and `chromium-driver` (/usr/bin/chromium, /usr/bin/chromedriver) and `selenium` (the
test extra); nothing is downloaded. `tests/test_view_browser.py` drives the page with the same helpers.
"""

from __future__ import annotations

import argparse
import shutil
import tempfile
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

from selenium import webdriver
from selenium.webdriver.chrome.service import Service
from selenium.webdriver.common.action_chains import ActionChains
from selenium.webdriver.common.keys import Keys
from selenium.webdriver.remote.webdriver import WebDriver
from selenium.webdriver.remote.webelement import WebElement
from selenium.webdriver.support.ui import WebDriverWait

CHROMIUM = shutil.which("chromium")
CHROMEDRIVER = shutil.which("chromedriver")
# No network, no background updates, no sandbox (CI runs as root), a fresh profile per session.
FLAGS = ("--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
         "--disable-background-networking", "--disable-component-update", "--disable-sync")


@contextmanager
def chromium(width: int = 1400, height: int = 1000) -> Iterator[WebDriver]:
    """A headless Chromium session with a W×H px window, driven through Debian's chromedriver (explicit paths:
    Selenium Manager would try to download a driver)."""
    options = webdriver.ChromeOptions()
    options.binary_location = CHROMIUM
    with tempfile.TemporaryDirectory(prefix="cvqpg-chromium-") as profile:
        for flag in (*FLAGS, f"--user-data-dir={profile}", f"--window-size={width},{height}"):
            options.add_argument(flag)
        driver = webdriver.Chrome(service=Service(CHROMEDRIVER), options=options)
        try:
            yield driver
        finally:
            driver.quit()


def open_page(driver: WebDriver, page: Path) -> None:
    """Load the page from its file and wait until every frame is decoded."""
    driver.get(page.resolve().as_uri())
    WebDriverWait(driver, 30).until(lambda d: d.execute_script(
        "return [...document.querySelectorAll('#view img')].every((i) => i.complete && i.naturalWidth > 0)"))


def drag(driver: WebDriver, element: WebElement, start: tuple[float, float], stop: tuple[float, float]) -> None:
    """Drag the mouse over `element` between two points given as fractions of its width and height."""
    size = element.size
    offset = [(round((f - 0.5) * size["width"]), round((g - 0.5) * size["height"])) for f, g in (start, stop)]
    (ActionChains(driver).move_to_element_with_offset(element, *offset[0]).click_and_hold()
     .move_by_offset(offset[1][0] - offset[0][0], offset[1][1] - offset[0][1]).release().perform())


def show_frame(driver: WebDriver, index: int) -> None:
    """Refocus to frame `index` with the arrow keys, as a user would."""
    body = driver.find_element("tag name", "body")
    current = int(driver.execute_script("return document.body.dataset.frame"))
    for _ in range(abs(index - current)):
        body.send_keys(Keys.ARROW_RIGHT if index > current else Keys.ARROW_LEFT)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("page", type=Path)
    parser.add_argument("out", type=Path)
    parser.add_argument("--index", type=int, default=None, help="frame to show [default: the first plane's]")
    parser.add_argument("--crop", type=float, nargs=4, metavar=("X0", "Y0", "X1", "Y1"),
                        help="crop corners as fractions of the image")
    parser.add_argument("--window", type=int, nargs=2, default=(1400, 1000), metavar=("W", "H"))
    args = parser.parse_args()
    with chromium(*args.window) as driver:
        open_page(driver, args.page)
        if args.index is not None:
            show_frame(driver, args.index)
        if args.crop:
            x0, y0, x1, y1 = args.crop
            drag(driver, driver.find_element("css selector", "#view .frame"), (x0, y0), (x1, y1))
        driver.save_screenshot(str(args.out))
    print(f"{args.out}: {args.window[0]}×{args.window[1]} px")


if __name__ == "__main__":
    main()
