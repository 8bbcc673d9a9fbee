"""The episodes page, the episodes fragment inside a page that loads plotly.js after it, and the
comparison page in a real headless browser, offline: no JavaScript error and every figure drawn
(plotly's SVG present). The harness is tests/test_report_browser.py's.

Skipped only when chromium is not installed; `.ci/run` installs it."""

from __future__ import annotations

from pathlib import Path

import pytest
from test_episodes_view import small_run
from test_report_browser import BROWSER, dump_dom

from tertiary.report import compare as cmp
from tertiary.report import episodes as ev

pytestmark = pytest.mark.skipif(BROWSER is None, reason="chromium is not installed (Debian: apt-get install chromium; "
                                                        ".ci/run installs it)")


def _drawn(page: Path, n: int) -> None:
    dom = dump_dom(page)
    assert dom.errors.strip() == "", f"JavaScript errors:\n{dom.errors}"
    assert dom.body.get("data-js-errors") == "0"
    assert dom.body.get("data-figures") == str(n)
    assert dom.body.get("data-rendered") == str(n), "not every figure finished drawing"
    assert len(dom.plots) == n and all(k >= 1 for k in dom.plots), f"plots without SVG: {dom.plots}"


def _plotly_last(page: str) -> str:
    """``page`` with its inline plotly.js moved to the end of the body, as in the report, where
    the episodes fragment may come before the first figure that carries plotly.js."""
    before, head_js, rest = page.split("<script>", 2)
    js, body = rest.split("</script>", 1)
    return f"{before}<script>{head_js}<script></script>{body.replace('</body>', f'<script>{js}</script></body>')}"


def test_episodes_page_renders_even_when_plotly_comes_after_it(tmp_path_factory, tmp_path):
    run = small_run(tmp_path_factory)
    page, k, _note = ev.render_episodes(run, n=2)
    assert k == 2
    late = _plotly_last(page)
    assert late.index("Plotly.newPlot") < late.index("plotly.js")
    path = tmp_path / "episodes.html"
    path.write_text(late)
    _drawn(path, k)


def test_compare_page_renders(tmp_path_factory, tmp_path):
    runs = [small_run(tmp_path_factory, "base"), small_run(tmp_path_factory, "fewer")]
    path, _table, _diff = cmp.write_compare(runs, tmp_path / "compare.html")
    _drawn(path, 1)
