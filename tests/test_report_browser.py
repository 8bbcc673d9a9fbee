"""The report in a real headless browser (Debian `chromium`): no JavaScript error, every figure
drawn, offline; a screenshot is kept as a test artefact (tests/artifacts/report.png).

Skipped only when chromium is not installed; `.ci/run` installs it.
"""

from __future__ import annotations

import dataclasses
import shutil
import subprocess
import tempfile
from html.parser import HTMLParser
from pathlib import Path

import pytest

from tertiary import pipeline
from tertiary.report.html import REPORT_FILENAME, build_report, figure_count
from tertiary.simulate import load_scenario, simulate

ARTIFACTS = Path(__file__).resolve().parent / "artifacts"
BROWSERS = ("chromium", "chromium-browser")
BROWSER = next((shutil.which(b) for b in BROWSERS if shutil.which(b)), None)

pytestmark = pytest.mark.skipif(BROWSER is None, reason="chromium is not installed (Debian: apt-get install chromium; "
                                                        ".ci/run installs it)")

FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
         "--disable-background-networking", "--disable-component-update", "--disable-sync",
         "--disable-dev-shm-usage", "--hide-scrollbars",
         # offline: any network request goes to a closed local port and fails
         "--proxy-server=http://127.0.0.1:9", "--proxy-bypass-list=<-loopback>"]
BUDGET_MS = 60_000


def chromium(*args: str, timeout: float = 180.0) -> subprocess.CompletedProcess:
    with tempfile.TemporaryDirectory(prefix="tertiary-chromium-") as profile:
        return subprocess.run([BROWSER, *FLAGS, f"--user-data-dir={profile}", *args], capture_output=True,
                              text=True, timeout=timeout, check=False)


class DomSummary(HTMLParser):
    """From a dumped DOM: body data attributes, the error <pre> text and, per plotly figure div
    (class js-plotly-plot), the number of <svg class="main-svg"> elements inside it."""

    VOID = {"area", "base", "br", "col", "embed", "hr", "img", "input", "link", "meta", "source", "track", "wbr"}

    def __init__(self) -> None:
        super().__init__()
        self.body: dict[str, str] = {}
        self.errors = ""
        self.plots: list[int] = []
        self._stack: list[tuple[str, int | None]] = []      # (tag, index of the plot it opens)
        self._open_plots: list[int] = []
        self._in_errors = False

    def handle_starttag(self, tag, attrs):
        a = {k: (v or "") for k, v in attrs}
        classes = a.get("class", "").split()
        if tag == "body":
            self.body = a
        if tag == "pre" and a.get("id") == "js-errors":
            self._in_errors = True
        if tag == "svg" and "main-svg" in classes and self._open_plots:
            self.plots[self._open_plots[-1]] += 1
        if tag in self.VOID:
            return
        plot = None
        if tag == "div" and "js-plotly-plot" in classes:
            plot = len(self.plots)
            self.plots.append(0)
            self._open_plots.append(plot)
        self._stack.append((tag, plot))

    def handle_startendtag(self, tag, attrs):
        self.handle_starttag(tag, attrs)
        if tag not in self.VOID:
            self.handle_endtag(tag)

    def handle_endtag(self, tag):
        if tag == "pre":
            self._in_errors = False
        while self._stack:
            t, plot = self._stack.pop()
            if plot is not None:
                self._open_plots.remove(plot)
            if t == tag:
                break

    def handle_data(self, data):
        if self._in_errors:
            self.errors += data


def dump_dom(html_file: Path) -> DomSummary:
    res = chromium(f"--virtual-time-budget={BUDGET_MS}", "--dump-dom", html_file.resolve().as_uri())
    assert res.returncode == 0, res.stderr[-2000:]
    assert "<body" in res.stdout, res.stderr[-2000:]
    dom = DomSummary()
    dom.feed(res.stdout)
    return dom


@pytest.fixture(scope="module")
def report(tmp_path_factory) -> Path:
    cfg = load_scenario("terminal-area")
    cfg = dataclasses.replace(cfg, duration_s=300.0, traffic=dataclasses.replace(cfg.traffic, aircraft=20,
                                                                                  conflict_pairs=3))
    out = tmp_path_factory.mktemp("browser_run")
    pipeline.run(simulate(cfg), out, pipeline.PipelineConfig())        # the main job's pictures (22)
    return build_report(out)


def test_report_renders_without_errors(report):
    n = figure_count(report.read_text())
    assert n >= 11
    dom = dump_dom(report)
    assert dom.errors.strip() == "", f"JavaScript errors:\n{dom.errors}"
    assert dom.body.get("data-js-errors") == "0"
    assert dom.body.get("data-figures") == str(n)
    assert dom.body.get("data-rendered") == str(n), "not every figure finished drawing"
    assert len(dom.plots) == n
    assert all(k >= 1 for k in dom.plots), f"empty plot elements: {dom.plots}"


def test_screenshot_artifact(report, tmp_path):
    png = tmp_path / "report.png"
    res = chromium(f"--virtual-time-budget={BUDGET_MS}", "--window-size=1400,4000", f"--screenshot={png}",
                   report.resolve().as_uri())
    assert res.returncode == 0, res.stderr[-2000:]
    data = png.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 50_000     # a blank page compresses to a few kB
    ARTIFACTS.mkdir(exist_ok=True)
    shutil.copyfile(png, ARTIFACTS / "report.png")


def test_javascript_errors_are_caught(report, tmp_path):
    """The harness itself: an error thrown in the page is reported, not silently passed."""
    broken = tmp_path / REPORT_FILENAME
    page = report.read_text()
    broken.write_text(page.replace("</body>", "<script>window.setTimeout(function () { null.boom(); }, 0);"
                                              "</script></body>"))
    dom = dump_dom(broken)
    assert "boom" in dom.errors or "null" in dom.errors
    assert dom.body.get("data-js-errors") == "1"
    assert dom.body.get("data-rendered") == dom.body.get("data-figures")


def test_verdict_matrix_fits_one_screen(report):
    """With the main job's pictures, the verdict (three lines, the failing cells, the matrix) ends
    above the fold of a 1400 × 900 window."""
    res = chromium(f"--virtual-time-budget={BUDGET_MS}", "--window-size=1400,900", "--dump-dom",
                   report.resolve().as_uri())
    assert res.returncode == 0, res.stderr[-2000:]
    dom = DomSummary()
    dom.feed(res.stdout)
    assert report.read_text().count('<th class="vm-pic">') == 22
    bottom = int(dom.body.get("data-verdict-bottom", "100000"))
    assert 0 < bottom <= 900, f"the verdict matrix ends at {bottom} px"
