"""The demo's and the fit's report.html in a real browser (headless Chromium, Debian's ``chromium``; .ci/run
installs it): every image loads, the summary is there and on the first screen, and the page renders."""

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


def _marks(report: Path, tmp_path: Path) -> dict[str, str]:
    """What the probe marked on <body> once the page (``report`` with the probe script added) loaded."""
    probed = tmp_path / "probed.html"  # the report with the probe script added before </body>
    probed.write_text(report.read_text().replace("</body>", _PROBE + "</body>"))
    dumped = _chromium("--dump-dom", probed.as_uri(), profile=tmp_path / "profile-dom")
    assert dumped.returncode == 0, dumped.stderr[-2000:]
    body = re.search(r"<body([^>]*)>", dumped.stdout)
    assert body, dumped.stdout[:2000]
    return dict(re.findall(r'data-([a-z-]+)="([^"]*)"', body.group(1)))


def _check_screenshot(report: Path, tmp_path: Path) -> Path:
    """Screenshot the first screen of ``report``, check that it shows a page; returns the PNG's path."""
    screenshot = tmp_path / f"{report.stem}.png"
    shot = _chromium(f"--screenshot={screenshot}", report.as_uri(), profile=tmp_path / "profile-shot")
    assert shot.returncode == 0, shot.stderr[-2000:]
    image = cv2.imread(str(screenshot))
    assert image is not None and image.shape[:2] == (WINDOW[1], WINDOW[0])
    assert image.std() > 20  # text and figures, not a blank page
    return screenshot


def test_every_image_loads_and_the_summary_is_on_the_first_screen(quick_demo, tmp_path: Path) -> None:
    _, output, _ = quick_demo
    report = output / "report.html"
    marks = _marks(report, tmp_path)
    assert int(marks["images"]) == 5
    assert marks["loaded"] == marks["images"], marks
    assert int(marks["summary-text"]) > 200  # the paragraph, not an empty element
    assert 0 <= int(marks["summary-top"]) < WINDOW[1] // 2, marks  # near the top of the first screen
    _check_screenshot(report, tmp_path)


@pytest.fixture(scope="module")
def fit_report_page(small_palpation, tmp_path_factory) -> Path:
    """``usdeform fit --report`` on the small palpation with its frames black below row 80 (so the page
    has warnings to show): the report's folder."""
    import dataclasses

    from usdeform.cli import main
    from usdeform.io import write_sequence

    recording, _ = small_palpation
    frames = recording.frames.copy()
    frames[:, 80:, :] = 0
    folder = tmp_path_factory.mktemp("fit-report")
    palpation = folder / "palpation.seq.nrrd"
    write_sequence(palpation, dataclasses.replace(recording, frames=frames))
    arguments = ["fit", str(palpation), "--output", str(folder / "model.json"), "--flexible-layer-mm", "50"]
    assert main([*arguments, "--report", str(folder / "report")]) == 0
    return folder / "report"


def test_the_fit_report_loads_its_figures_and_shows_the_warnings_first(fit_report_page: Path, tmp_path: Path) -> None:
    report = fit_report_page / "report.html"
    marks = _marks(report, tmp_path)
    assert int(marks["images"]) == 4  # tracks per band, field, stiffness, cross-validation
    assert marks["loaded"] == marks["images"], marks
    assert int(marks["summary-text"]) > 100  # the counts and the warnings, not an empty element
    assert 0 <= int(marks["summary-top"]) < WINDOW[1] // 2, marks
    _check_screenshot(report, tmp_path)
