"""Drive nerfstudio's viewer (viser web client) in headless Debian chromium through playwright.

Used by ``tests/test_viewer.py`` and ``tests/browser/make_screenshot.py``. Needs
``apt-get install -y chromium`` and ``pip install playwright`` (never ``playwright install``:
we launch the system chromium).

Waits are Playwright's own (locators and ``expect`` wait until their condition holds); only the
rendered image, which lives in a WebGL canvas and not in the page's DOM, is polled by screenshot.

Two records of a render: the screenshot (what the user sees) and the image the browser received
(viser's ``BackgroundImageMessage`` on the websocket, decoded). Screenshots of one and the same
received image differ from capture to capture by up to 1.9 grey levels on average (2026-11-26, 1a660fb:
the server's images compared equal while the screenshots did not), so equality of two renders is
asserted on the received images, and the screenshots show that the canvas changes.
"""

from __future__ import annotations

import io
import re
import shutil
import socket
import subprocess
import tempfile
import time
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator, Optional, Tuple

import numpy as np

CHROMIUM = "/usr/bin/chromium"
CHROMIUM_ARGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
]
RESOLUTION = re.compile(r"Resolution:\s*(\d+)x(\d+)px")


def chromium_path() -> Optional[str]:
    return CHROMIUM if Path(CHROMIUM).exists() else shutil.which("chromium")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_for_port(port: int, proc: Optional[subprocess.Popen] = None, timeout: float = 300.0) -> None:
    """Until something accepts connections on 127.0.0.1:port (or ``proc`` dies)."""
    deadline = time.time() + timeout
    while time.time() < deadline:
        if proc is not None and proc.poll() is not None:
            raise RuntimeError(f"viewer exited with {proc.returncode} before listening")
        try:
            socket.create_connection(("127.0.0.1", port), timeout=1.0).close()
            return
        except OSError:
            time.sleep(0.5)
    raise TimeoutError(f"nothing listens on 127.0.0.1:{port} after {timeout:.0f} s")


@contextmanager
def browser_page(width: int = 1000, height: int = 700) -> Iterator["object"]:
    """A fresh headless chromium (own user-data-dir) and one page of the given size."""
    from playwright.sync_api import sync_playwright

    executable = chromium_path()
    assert executable, "chromium is not installed (apt-get install -y chromium)"
    with tempfile.TemporaryDirectory(prefix="chromium-profile-") as profile, sync_playwright() as p:
        context = p.chromium.launch_persistent_context(
            profile,
            executable_path=executable,
            headless=True,
            args=CHROMIUM_ARGS,
            viewport={"width": width, "height": height},
        )
        try:
            # The viser client asks the internet for the nerfstudio logo: never wait for it.
            context.route(re.compile(r"^https?://(?!127\.0\.0\.1|localhost)"), lambda route: route.abort())
            yield context.pages[0] if context.pages else context.new_page()
        finally:
            context.close()


def decode_png(data: bytes) -> np.ndarray:
    import imageio.v3 as iio

    return np.asarray(iio.imread(io.BytesIO(data), extension=".png"))[..., :3]


def mean_abs_diff(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.abs(a.astype(np.float64) - b.astype(np.float64)).mean())


def background_images(frame: bytes) -> list:
    """The background images (RGB uint8) in one viser websocket frame: a msgpack message, or a
    tuple of them (client API 1)."""
    import msgspec

    decoded = msgspec.msgpack.decode(frame)
    messages = decoded if isinstance(decoded, (list, tuple)) else [decoded]
    return [
        decode_png(m["rgb_bytes"])
        for m in messages
        if isinstance(m, dict) and m.get("type") == "BackgroundImageMessage" and m.get("media_type") == "image/png"
    ]


class ViewerPage:
    """nerfstudio's viewer page: its GUI controls, the rendered image, and the images received."""

    def __init__(self, page, url: str) -> None:
        self.page = page
        self.url = url
        self.received: list = []  # every background image the page was sent, in order
        page.on("websocket", lambda socket: socket.on("framereceived", self._record))

    def _record(self, payload) -> None:
        if isinstance(payload, (bytes, bytearray)):
            self.received.extend(background_images(bytes(payload)))

    def open(self, timeout: float = 120.0) -> None:
        self.page.goto(self.url, wait_until="domcontentloaded", timeout=timeout * 1000)
        self.page.get_by_text("Output type", exact=True).first.wait_for(timeout=timeout * 1000)

    # --- controls -------------------------------------------------------------------------

    def _label(self, text: str):
        return self.page.locator("label").filter(has_text=re.compile(rf"^\s*{re.escape(text)}\s*$")).first

    def wait_for_label(self, text: str, timeout: float = 120.0) -> None:
        self._label(text).wait_for(state="attached", timeout=timeout * 1000)

    def has_control(self, text: str) -> bool:
        return self._label(text).count() > 0 and self._label(text).is_visible()

    def checkbox(self, text: str):
        return self.page.locator(f'[id="{self._label(text).get_attribute("for")}"]')

    def click_checkbox(self, text: str) -> bool:
        """Toggle a checkbox; returns its new state (once the page shows it)."""
        from playwright.sync_api import expect

        box = self.checkbox(text)
        was_checked = box.is_checked()
        box.click()  # scrolls it into view and waits until it can be clicked
        expect(box).to_be_checked(checked=not was_checked)
        return box.is_checked()

    def slider_thumb(self, text: str):
        slider_id = self._label(text).get_attribute("for")
        return self.page.locator(f'[id="{slider_id}"] [role="slider"]')

    def slider_to_min(self, text: str) -> float:
        """Move a slider to its minimum with the keyboard (Home); returns its value (once the
        page shows it)."""
        from playwright.sync_api import expect

        thumb = self.slider_thumb(text)
        thumb.scroll_into_view_if_needed()
        thumb.press("Home")
        expect(thumb).to_have_attribute("aria-valuenow", thumb.get_attribute("aria-valuemin"))
        return float(thumb.get_attribute("aria-valuenow"))

    def dropdown_value(self, text: str) -> str:
        """The option a dropdown shows."""
        return self.page.locator(f'[id="{self._label(text).get_attribute("for")}"]').input_value()

    def dropdown_options(self, text: str) -> list:
        """The options of a dropdown (opens and closes it)."""
        box = self.page.locator(f'[id="{self._label(text).get_attribute("for")}"]')
        box.scroll_into_view_if_needed()
        box.click()
        options = self.page.get_by_role("option")
        options.first.wait_for(timeout=10_000)
        texts = [t.strip() for t in options.all_inner_texts()]
        self.page.keyboard.press("Escape")
        options.first.wait_for(state="hidden")
        return texts

    def choose_option(self, text: str, option: str) -> None:
        """Select ``option`` in a dropdown."""
        box = self.page.locator(f'[id="{self._label(text).get_attribute("for")}"]')
        box.scroll_into_view_if_needed()
        box.click()
        self.page.get_by_role("option", name=option, exact=True).click()

    def show_label(self, text: str) -> None:
        """Scroll the control panel until this control is in view."""
        from playwright.sync_api import expect

        self._label(text).scroll_into_view_if_needed()
        expect(self._label(text)).to_be_in_viewport()

    # --- the rendered image ---------------------------------------------------------------

    def resolution(self) -> Optional[Tuple[int, int]]:
        """The render resolution nerfstudio reports (width, height), None before the first one."""
        match = RESOLUTION.search(self.page.locator("body").inner_text())
        if not match or match.group(1) == "0":
            return None
        return int(match.group(1)), int(match.group(2))

    def canvas_box(self) -> dict:
        """Page region of the 3D view: the canvas, left of the control panel (which floats
        over the canvas)."""
        boxes = [c.bounding_box() for c in self.page.locator("canvas").all()]
        box = dict(max((b for b in boxes if b), key=lambda b: b["width"] * b["height"]))
        panel_left = self.page.get_by_text("Output type", exact=True).first.evaluate(
            """(el) => {
                for (let e = el; e; e = e.parentElement) {
                    const pos = getComputedStyle(e).position;
                    if (pos === "absolute" || pos === "fixed") return e.getBoundingClientRect().left;
                }
                return null;
            }"""
        )
        if panel_left is not None and box["x"] < panel_left < box["x"] + box["width"]:
            box["width"] = panel_left - box["x"]
        return box

    def view(self, margin: int = 8) -> np.ndarray:
        """Screenshot of the 3D view (RGB uint8)."""
        b = self.canvas_box()
        clip = {
            "x": b["x"] + margin,
            "y": b["y"] + margin,
            "width": b["width"] - 2 * margin,
            "height": b["height"] - 2 * margin,
        }
        return decode_png(self.page.screenshot(clip=clip))

    def wait_for_render(
        self,
        max_res: int,
        previous: Optional[np.ndarray] = None,
        min_change: float = 1.0,
        settle: float = 1.0,
        timeout: float = 180.0,
    ) -> np.ndarray:
        """Until the full-resolution render (larger side ``max_res``) is shown, differs from
        ``previous`` by at least ``min_change`` (mean abs, 0-255) and has not changed for
        ``settle`` seconds. Returns that view.

        The resolution nerfstudio reports is waited for by Playwright; the pixels are polled
        (screenshots), as no DOM state says that a render has reached the canvas."""
        from playwright.sync_api import expect

        full = re.compile(rf"Resolution:\s*({max_res}x\d+|\d+x{max_res})px")
        expect(self.page.locator("body")).to_contain_text(full, timeout=timeout * 1000)
        deadline = time.time() + timeout
        stable_since, last = None, None
        while time.time() < deadline:
            res, shot = self.resolution(), self.view()
            done = res is not None and max(res) == max_res  # not a low-resolution render on the way
            done = done and (previous is None or mean_abs_diff(shot, previous) >= min_change)
            if done and last is not None and mean_abs_diff(shot, last) == 0.0:
                stable_since = stable_since or time.time()
                if time.time() - stable_since >= settle:
                    return shot
            else:
                stable_since = None
            last = shot
            self.page.wait_for_timeout(250)  # screenshot poll interval
        raise TimeoutError(f"no new {max_res}px render within {timeout:.0f} s (resolution {self.resolution()})")

    def last_received(self, max_res: int) -> np.ndarray:
        """The last image the page was sent, which must be a full-resolution one (larger side ``max_res``)."""
        assert self.received, "the page received no background image (png) over the websocket"
        image = self.received[-1]
        assert max(image.shape[:2]) == max_res, f"the last image received is {image.shape[1]}x{image.shape[0]}"
        return image
