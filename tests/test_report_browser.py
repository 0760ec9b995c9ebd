"""The demo's report.html in a real browser (headless Chromium, Debian's ``chromium``; .ci/run installs it):
every image loads, the summary is there and on the first screen, and the page renders."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
from pathlib import Path

import cv2
import pytest

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
WINDOW = (1280, 900)

# On CI (.ci/run installs chromium) a missing browser fails the test instead of skipping it.
pytestmark = pytest.mark.skipif(
    CHROMIUM is None and os.environ.get("CI") != "true", reason="chromium is not installed (.ci/run installs it)"
)

# Marks on <body>, after the page and its images finished loading, what a user would see.
_PROBE = """<script>
window.addEventListener("load", () => {
  const images = Array.from(document.images);
  const summary = document.getElementById("summary");
  document.body.dataset.images = images.length;
  document.body.dataset.loaded = images.filter((image) => image.complete && image.naturalWidth > 0).length;
  document.body.dataset.summaryTop = summary ? Math.round(summary.getBoundingClientRect().top) : -1;
  document.body.dataset.summaryText = summary ? summary.innerText.length : 0;
});
</script>"""


def _chromium(*arguments: str, profile: Path) -> subprocess.CompletedProcess[str]:
    assert CHROMIUM is not None, "chromium is not installed: .ci/run installs it with apt-get"
    return subprocess.run(
        [
            CHROMIUM,
            "--headless",
            "--no-sandbox",  # CI runs as root
            "--disable-gpu",
            "--hide-scrollbars",
            f"--user-data-dir={profile}",
            f"--window-size={WINDOW[0]},{WINDOW[1]}",
            "--virtual-time-budget=10000",
            *arguments,
        ],
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )


def test_every_image_loads_and_the_summary_is_on_the_first_screen(quick_demo, tmp_path: Path) -> None:
    _, output, _ = quick_demo
    report = output / "report.html"
    probed = tmp_path / "probed.html"  # the report with the probe script added before </body>
    probed.write_text(report.read_text().replace("</body>", _PROBE + "</body>"))

    dumped = _chromium("--dump-dom", probed.as_uri(), profile=tmp_path / "profile-dom")
    assert dumped.returncode == 0, dumped.stderr[-2000:]
    body = re.search(r"<body([^>]*)>", dumped.stdout)
    assert body, dumped.stdout[:2000]
    marks = dict(re.findall(r'data-([a-z-]+)="([^"]*)"', body.group(1)))
    assert int(marks["images"]) == 5
    assert marks["loaded"] == marks["images"], marks
    assert int(marks["summary-text"]) > 200  # the paragraph, not an empty element
    assert 0 <= int(marks["summary-top"]) < WINDOW[1] // 2, marks  # near the top of the first screen

    screenshot = tmp_path / "report.png"
    shot = _chromium(f"--screenshot={screenshot}", report.as_uri(), profile=tmp_path / "profile-shot")
    assert shot.returncode == 0, shot.stderr[-2000:]
    image = cv2.imread(str(screenshot))
    assert image is not None and image.shape[:2] == (WINDOW[1], WINDOW[0])
    assert image.std() > 20  # text and figures, not a blank page
