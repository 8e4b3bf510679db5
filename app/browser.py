"""Headless Chromium for the page's browser tests, screenshots and benchmark: which browser, its flags, how to
find a viser control's input by its label, and how to close the notice headless Chromium gets."""

from __future__ import annotations

import os
import re
import shutil

CHROMIUM = os.environ.get("GSMN_CHROMIUM") or shutil.which("chromium") or shutil.which("chromium-browser")
CHROMIUM_ARGS = ["--no-sandbox", "--disable-gpu", "--disable-background-networking", "--disable-component-update",
                 "--disable-sync", "--disable-quic", "--no-first-run", "--enable-unsafe-swiftshader"]


def field(page, label: str):
    """The input of a labelled viser control (viser's <label for> does not point at text inputs)."""
    return page.locator("label").filter(has_text=re.compile(f"^{re.escape(label)}$")).first.locator(
        "xpath=ancestor::div[contains(@class,'mantine-Flex-root')][1]//input").first


def dismiss_notifications(page) -> None:
    """Close the "software WebGL" notice headless Chromium gets (a browser with a GPU does not)."""
    page.evaluate("""() => document.querySelectorAll('.mantine-Notification-closeButton, '
                  + '[class*="Notification"] button').forEach(b => b.click())""")
