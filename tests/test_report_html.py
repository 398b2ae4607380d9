"""`labrunner report`: one self-contained HTML file per campaign, checked as text and rendered in
headless Chromium (issue 14, item 2). The browser part is skipped only where chromium is not
installed; `.ci/run` installs Debian's."""

from __future__ import annotations

import re
import shutil
import subprocess
import sys
import time
from html.parser import HTMLParser
from importlib.resources import files
from pathlib import Path

import numpy as np
import pytest

import labrunner
from labrunner.report_html import SECTIONS, ReportResult

TINY = """\
name: tiny
temperatures: {{list_c: [15, 35]}}
soak: {{tolerance_c: 0.5, stable_window_s: 120, max_wait_s: 7200, on_timeout: continue, poll_s: 30}}
orientations: [x_up, x_down, y_up, y_down, z_up, z_down]
remount_s: 60
rates: {{list_dps: [-50, 0, 50]}}
settle_s: 1
record_s: 4
record_poll_s: 2
fit: {{run: {fit}}}
"""
FIGURES = ("thermal_accel_bias", "thermal_accel_scale", "thermal_gyro_bias", "thermal_gyro_scale",
           "heldout_error_accel", "heldout_error_gyro", "static_norm_accel", "static_norm_gyro", "allan_deviation")
CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
CHROMIUM_FLAGS = ("--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                  "--disable-background-networking", "--disable-component-update", "--disable-sync")


class Page(HTMLParser):
    """Ids, image sources, links and table row counts of a document."""

    def __init__(self, text: str) -> None:
        super().__init__()
        self.ids: set[str] = set()
        self.sources: list[str] = []
        self.links: list[str] = []
        self.rows: dict[str, int] = {}
        self._table: list[str] = []
        self.feed(text)

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        a = dict(attrs)
        if a.get("id"):
            self.ids.add(str(a["id"]))
        if tag == "img":
            self.sources.append(str(a.get("src")))
        if tag in ("a", "link", "script", "iframe") and (a.get("href") or a.get("src")):
            self.links.append(str(a.get("href") or a.get("src")))
        if tag == "table":
            self._table.append(str(a.get("id", f"table{len(self.rows)}")))
        if tag == "tr" and self._table:
            self.rows[self._table[-1]] = self.rows.get(self._table[-1], 0) + 1

    def handle_endtag(self, tag: str) -> None:
        if tag == "table" and self._table:
            self._table.pop()


@pytest.fixture(scope="module")
def quick(tmp_path_factory: pytest.TempPathFactory) -> Path:
    d = tmp_path_factory.mktemp("report")
    result = labrunner.run(files("labrunner.procedures") / "quick.yaml", db=d / "quick.db", seed=1)
    assert result.state == "done" and result.fit_ok
    return d


@pytest.fixture(scope="module")
def stopped(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Campaign 1 paused after five steps (its end-of-run fit not reached); campaign 2 done without a fit."""
    d = tmp_path_factory.mktemp("stopped")
    (d / "fit.yaml").write_text(TINY.format(fit="true"))
    (d / "nofit.yaml").write_text(TINY.format(fit="false"))
    with labrunner.start_run(d / "fit.yaml", db=d / "s.db") as session:
        def pause_after_five(progress: labrunner.Progress) -> None:
            if progress.steps_done == 5:
                session.request_pause("test: pause after five steps")

        assert session.execute(pause_after_five).state == "paused"
    assert labrunner.run(d / "nofit.yaml", db=d / "s.db").state == "done"
    return d


def _check_self_contained(text: str, page: Page) -> None:
    assert not re.search(r"https?://", text), "a reference to an external resource"
    assert not re.search(r"url\(|@import", text), "CSS that could fetch something"
    assert page.sources and all(s.startswith("data:image/png;base64,") for s in page.sources)
    assert all(link.startswith("#") for link in page.links), page.links


@pytest.fixture(scope="module")
def quick_report(quick: Path) -> tuple[Path, ReportResult]:
    t0 = time.perf_counter()
    result = labrunner.report(quick / "quick.db", html=quick / "quick.html")
    assert time.perf_counter() - t0 < 20  # ~4 s here; generous for a loaded CI machine
    return quick / "quick.html", result


def test_quick_report_has_every_section(quick_report: tuple[Path, ReportResult]) -> None:
    path, result = quick_report
    text = path.read_text()
    page = Page(text)
    _check_self_contained(text, page)
    assert set(SECTIONS) <= page.ids
    assert {"fig-overview", *(f"fig-{f}" for f in FIGURES)} <= page.ids
    assert page.rows["steps-table"] == 192 + 1  # every planned step, and the header
    assert page.rows["events-table"] > 192  # at least one record event per step
    assert "Campaign 1 &#x27;quick&#x27; — done" in text or "Campaign 1 'quick' — done" in text
    assert "Exported model: <b>rbf_hybrid</b>" in text and "over raw" in text
    assert re.search(r"procedure SHA-256</td><td>[0-9a-f]{64}<", text)
    assert "The store keeps no diagnoses" in text  # said, not silently left out
    assert result.explained == {"diagnosis": "the store keeps no diagnoses"}
    assert "Refit" not in text and "differ from the stored ones" not in text  # the refit is the stored fit


def test_paused_and_unfitted_campaigns_say_why(stopped: Path) -> None:
    db = stopped / "s.db"
    paused = labrunner.report(db, html=stopped / "paused.html", campaign=1)
    assert paused.status == "paused" and paused.explained["calibration"] == "no stored fit"
    text = (stopped / "paused.html").read_text()
    page = Page(text)
    _check_self_contained(text, page)
    assert set(SECTIONS) <= page.ids and "fig-overview" in page.ids
    assert "the campaign is paused: the end-of-run fit runs when it finishes" in text
    assert page.rows["steps-table"] == 36 + 1
    assert text.count("<td>done</td>") == 5 and "pause after five steps" in text

    labrunner.report(db, html=stopped / "nofit.html", campaign=2)
    text = (stopped / "nofit.html").read_text()
    assert "Campaign 2 " in text and "the procedure turns the end-of-run fit off" in text
    assert not any(f"fig-{f}" in text for f in FIGURES)


def test_campaign_without_samples(tmp_path: Path) -> None:
    """A lab that does not answer: the campaign pauses in preflight with no sample; the report says so."""
    (tmp_path / "tiny.yaml").write_text(TINY.format(fit="true"))
    (tmp_path / "nowhere.yaml").write_text(
        "name: nowhere\n"  # closed loopback ports: refused at once, no network needed
        "chamber: {transport: tcp, host: 127.0.0.1, port: 1, device_id: 1, timeout_s: 0.2, retries: 0}\n"
        "table: {port: 'socket://127.0.0.1:2'}\nimu: {port: 'socket://127.0.0.1:3', rate_hz: 50}\n")
    run = labrunner.run(tmp_path / "tiny.yaml", lab=tmp_path / "nowhere.yaml", db=tmp_path / "n.db")
    assert run.state == "paused" and run.samples == 0
    result = labrunner.report(tmp_path / "n.db", html=tmp_path / "n.html")
    assert set(result.explained) == {"overview", "calibration", "diagnosis"} and result.figures == []
    text = (tmp_path / "n.html").read_text()
    page = Page(text)
    assert set(SECTIONS) <= page.ids and "fig-overview" not in page.ids
    assert "No overview: no samples recorded yet" in text and "Last warning or fault: " in text
    assert page.rows["steps-table"] == 12 * 3 + 1 and text.count("<td>planned</td>") == 36


def test_cli_refuses_overwriting(stopped: Path) -> None:
    def report(*argv: str) -> subprocess.CompletedProcess[str]:
        return subprocess.run([sys.executable, "-m", "labrunner", "report", "s.db", *argv], cwd=stopped,
                              capture_output=True, text=True, timeout=120)

    first = report("--campaign", "2", "--html", "cli.html")
    assert first.returncode == 0 and "report written to cli.html" in first.stdout, first.stderr
    again = report("--campaign", "2", "--html", "cli.html")
    assert again.returncode == 2 and "--force" in again.stderr
    assert report("--html", "s.db", "--force").returncode == 2  # never the store
    assert report("--campaign", "2", "--html", "cli.html", "--force").returncode == 0
    assert report("--campaign", "9", "--html", "x.html").returncode == 2


def _chromium(args: list[str], cwd: Path) -> subprocess.CompletedProcess[str]:
    assert CHROMIUM is not None
    return subprocess.run([CHROMIUM, *CHROMIUM_FLAGS, f"--user-data-dir={cwd / 'chromium-profile'}", *args],
                          cwd=cwd, capture_output=True, text=True, timeout=120)


@pytest.mark.skipif(CHROMIUM is None, reason="chromium is not installed here (.ci/run installs Debian's)")
def test_quick_report_renders_in_chromium(quick_report: tuple[Path, ReportResult],
                                          tmp_path: Path) -> None:
    import matplotlib.image

    path, _ = quick_report
    url = path.resolve().as_uri()
    dom = _chromium(["--dump-dom", url], tmp_path)
    assert dom.returncode == 0, dom.stderr[-2000:]
    page = Page(dom.stdout)
    assert {"headline", "fig-overview", "steps-table", "events-table", *(f"fig-{f}" for f in FIGURES)} <= page.ids
    assert page.rows["steps-table"] == 193
    assert "Exported model:" in dom.stdout and "rows</span>" in dom.stdout  # the filter's row count

    shot = tmp_path / "report.png"
    rendered = _chromium([f"--screenshot={shot}", "--window-size=1280,4000", url], tmp_path)
    assert rendered.returncode == 0 and shot.is_file(), rendered.stderr[-2000:]
    pixels = matplotlib.image.imread(shot)[..., :3]
    assert pixels.shape[:2] == (4000, 1280)
    ink = (pixels < 0.9).any(axis=2)
    assert ink.mean() > 0.05, "the rendered page is (nearly) blank"
    # Figures drawn, not only text: many colours, and ink in the lower half (the calibration figures).
    colours = np.unique((pixels[::4, ::4] * 255).astype(np.uint8).reshape(-1, 3), axis=0)
    assert len(colours) > 200
    assert ink[2000:].mean() > 0.03
