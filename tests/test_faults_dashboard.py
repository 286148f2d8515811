"""Text from files and stores in the dashboard: a drive folder, a store file or a path typed into
"Other store" named like HTML or Markdown reaches the page as text, never as markup or script.
And the page opens only stores inside the folders it was started with (``--allow``).

One dashboard (``visloc dashboard`` in a subprocess) serves the text cases, on a store holding two
CSV drives with hostile folder names and itself named like markup; one headless Chromium page
looks at it. Another serves the folders cases; a third, on 0.0.0.0, only prints its warning.
Screenshots go to ``out/screenshots/faults_*.png``.
"""

from __future__ import annotations

import hashlib
import os
import re
import shutil
import signal
import socket
import sqlite3
import subprocess
import sys
import threading
from dataclasses import dataclass
from pathlib import Path

import pytest
from fault_table import Fault, params
from helpers import (
    SERVER_WORK_S,
    URL_LINE,
    DashboardProcess,
    control,
    dismiss_webgl_notice,
    open_other_store,
    open_page,
    screenshot,
    wait_for,
)

from helpers import REPO, run_cli, write_csv_drive

# Folder and file names: valid on Linux (no '/'), each a different way in. Whatever runs sets
# window.__xss; what Markdown would make of a name is an element inside the panel showing it.
HTML_DRIVE = '<iframe srcdoc="<img src=x onerror=parent.__xss=1>">'
MARKDOWN_DRIVE = "a_b_c *bold* [link](javascript:window.__xss=3) ![pic](x) www.example.com"
STORE_FILE = "<img src=x onerror=window.__xss=4> __store__.sqlite"
MISSING_HTML = "<img src=x onerror=window.__xss=2>.sqlite"
MISSING_MARKDOWN = "*not* a [store](javascript:window.__xss=5) ![pic](x).sqlite"

FAULTS = [
    Fault(id="dashboard-drive-folder-html", area="dashboard",
          tried="A drive whose folder is named like an HTML frame with a script in it",
          gets="The store panel and the dataset lists show the folder name as text; nothing runs"),
    Fault(id="dashboard-drive-folder-markdown", area="dashboard",
          tried="A drive whose folder name holds Markdown: underscores, stars, a link, an image and a web address",
          gets="The name shows character for character; no emphasis, link or image is made of it"),
    Fault(id="dashboard-store-file-name", area="dashboard",
          tried="A store file named like an HTML image with a script, and with Markdown underscores",
          gets="The store panel and the store list show its path as text; nothing runs"),
    Fault(id="dashboard-other-store-html", area="dashboard",
          tried="Opening another store at a missing path named like an HTML image with a script",
          gets="The error message shows the path as text and nothing runs; the data shown stays"),
    Fault(id="dashboard-other-store-markdown", area="dashboard",
          tried="Opening another store at a missing path whose name holds Markdown stars, a link and an image",
          gets="The error message shows the path character for character; the data shown stays"),
    Fault(id="dashboard-writes-nothing", area="store file",
          tried="The dashboard on a store: matching every query of the first run",
          gets="The store file stays byte for byte the same: counts are kept in memory, never saved into the store"),
    Fault(id="dashboard-path-outside", area="dashboard",
          tried="Opening a store outside the folders the dashboard may open: a copy in a sibling folder, a path "
                "climbing out with ../, a symbolic link inside an allowed folder pointing out",
          gets="Refused with one line in the page naming the path and the folders it may open; the store shown "
               "stays, and the store list offers only stores inside; a store in an allowed folder still opens"),
    Fault(id="dashboard-public-host-warning", area="dashboard",
          tried="visloc dashboard --host 0.0.0.0 (reachable from other machines)",
          gets="A warning on stderr naming the port and the folders anyone reaching it can open, and the SSH "
               "tunnel to use instead"),
]


@dataclass(frozen=True)
class Case:
    where: str  # "dataset" or "store path" (shown from the start), or "other store" (typed in, then Open)
    name: str  # the injected text: a folder name, or a file name in the store's folder
    marker: str  # what its script would set: tells this case's injected elements from the others'


CASES = {
    "dashboard-drive-folder-html": Case("dataset", HTML_DRIVE, "__xss=1"),
    "dashboard-drive-folder-markdown": Case("dataset", MARKDOWN_DRIVE, "__xss=3"),
    "dashboard-store-file-name": Case("store path", STORE_FILE, "__xss=4"),
    "dashboard-other-store-html": Case("other store", MISSING_HTML, "__xss=2"),
    "dashboard-other-store-markdown": Case("other store", MISSING_MARKDOWN, "__xss=5"),
}

# markup made of a name anywhere in the page: a frame or embedded document, a handler attribute
# (the page has none of its own), a link, source or script carrying the name's marker
INJECTED = """(marker) => {
  const found = [];
  for (const el of document.querySelectorAll('iframe, frame, object, embed')) found.push(el.outerHTML.slice(0, 300));
  for (const el of document.querySelectorAll('script')) {
    if (el.textContent.includes(marker)) found.push(el.outerHTML.slice(0, 300));
  }
  const urls = ['href', 'src', 'srcdoc', 'srcset', 'action', 'formaction', 'data', 'xlink:href', 'poster'];
  for (const el of document.querySelectorAll('*')) {
    for (const a of el.attributes) {
      if (a.name.startsWith('on') || (urls.includes(a.name) && a.value.includes(marker))) {
        found.push(a.name + ' of ' + el.outerHTML.slice(0, 300));
      }
    }
  }
  return found;
}"""
# elements Markdown would make of a name, inside the element that shows it
MARKUP = "a, img, iframe, em, strong, code, script, del"


class Served:
    def __init__(self, folder: Path, store: Path, proc: DashboardProcess, digest_before: str):
        self.folder, self.store, self.proc, self.digest_before = folder, store, proc, digest_before


def digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


@pytest.fixture(scope="module")
def served(tmp_path_factory):
    """Two CSV drives in hostile folders, ingested into a hostile store file, served once."""
    folder = tmp_path_factory.mktemp("hostile")
    store = folder / STORE_FILE
    for name in (HTML_DRIVE, MARKDOWN_DRIVE):
        csv = write_csv_drive(folder / name, n_frames=6)
        result = run_cli("ingest", csv, "--db", store, "--workers", "1")
        assert result.returncode == 0, result.stderr
    before = digest(store)
    proc = DashboardProcess("--db", str(store), "--port", "8380")
    yield Served(folder, store, proc, before)
    proc.stop()


@pytest.fixture(scope="module")
def hostile_page(served, browser):
    page = open_page(browser, served.proc.url)  # waits for the first run to be ready
    dismiss_webgl_notice(page)
    page.get_by_text("Data", exact=True).click()  # the store panel's folder opens
    page.get_by_text(re.compile("^SIFT settings:")).wait_for()
    yield page
    page.close()


def store_panel(page):
    return page.get_by_text(re.compile("^SIFT settings:")).locator("xpath=..")


@pytest.mark.slow
@pytest.mark.parametrize("fault", params([f for f in FAULTS if f.id in CASES]))
def test_file_and_store_text_reaches_the_page_as_text(fault, served, hostile_page):
    case, page = CASES[fault.id], hostile_page
    panel = store_panel(page)
    if case.where == "other store":
        path = str(served.folder / case.name)
        shown = open_other_store(page, path)  # found by the path as written, after "⚠ "
        assert "does not exist" in shown.inner_text()
        # the data already shown stays
        assert control(page, "Store file").locator("input").first.input_value() == str(served.store)
        assert "6 images over 2.5 s" in panel.inner_text()
    elif case.where == "dataset":
        dataset = f"{case.name}/camera"  # source/camera; a CSV drive's source is its folder's name
        assert dataset in panel.inner_text(), "the dataset's name does not show as written"
        shown = panel.locator("li").filter(has_text=dataset)
        assert shown.count() == 1
        control(page, "Database").locator("input").first.click()  # the list offers it by its name
        option = page.get_by_role("option", name=dataset, exact=True)
        option.wait_for()
        page.keyboard.press("Escape")
        option.wait_for(state="hidden")
    else:
        shown = panel.locator("xpath=./*[1]")  # the panel's first line names the store file
        assert shown.inner_text() == str(served.store), "the store's path does not show as written"
        assert control(page, "Store file").locator("input").first.input_value() == str(served.store)
    assert shown.locator(MARKUP).count() == 0, shown.inner_html()[:2000]
    assert page.evaluate("window.__xss") is None, "a script from a name ran in the page"
    assert page.evaluate(INJECTED, case.marker) == [], "an element was made from a name"
    shown.scroll_into_view_if_needed()
    screenshot(page, f"faults_{fault.id}.png")
    assert served.proc.alive()


@pytest.mark.slow
@pytest.mark.parametrize("fault", params([f for f in FAULTS if f.id == "dashboard-writes-nothing"]))
def test_the_dashboard_never_writes_into_the_store(fault, served, hostile_page):
    # hostile_page waited for the first run to be ready: every query of it was matched
    assert digest(served.store) == served.digest_before
    conn = sqlite3.connect(served.store.as_uri() + "?mode=ro", uri=True)
    try:
        assert conn.execute("SELECT count(*) FROM pair_counts").fetchone()[0] == 0
    finally:
        conn.close()


# -- what the page may open ---------------------------------------------------------------------------------

OUTSIDE = "{}: outside the folders this dashboard may open ({}); restart it with --allow to add one"


class Fenced:
    def __init__(self, base: Path, proc: DashboardProcess):
        self.allowed, self.more, self.outside = base / "allowed", base / "more", base / "outside"
        self.store, self.proc = self.allowed / "drives.sqlite", proc


def make_fenced_folders(base: Path) -> None:
    """allowed/ (the store, a copy, a link to outside/), more/ (a second store), outside/ (a copy)."""
    for name in ("allowed", "more", "outside"):
        (base / name).mkdir()
    store = base / "allowed" / "drives.sqlite"
    for name, offset_px in (("drive_a", 0), ("drive_b", 30)):
        csv = write_csv_drive(base / name, n_frames=6, offset_px=offset_px)
        result = run_cli("ingest", csv, "--db", store, "--workers", "1")
        assert result.returncode == 0, result.stderr
    for copy in ("allowed/copy.sqlite", "more/second.sqlite", "outside/drives.sqlite"):
        shutil.copyfile(store, base / copy)
    (base / "allowed" / "link.sqlite").symlink_to(base / "outside" / "drives.sqlite")


@pytest.fixture(scope="module")
def fenced(tmp_path_factory):
    """A dashboard that may open allowed/ and more/ (two --allow), on a store in allowed/."""
    base = tmp_path_factory.mktemp("fenced")
    make_fenced_folders(base)
    proc = DashboardProcess("--db", str(base / "allowed" / "drives.sqlite"), "--allow", str(base / "allowed"),
                            "--allow", str(base / "more"), "--port", "8390")
    yield Fenced(base, proc)
    proc.stop()


def store_options(page) -> list[str]:
    """The stores the "Store file" list offers."""
    control(page, "Store file").locator("input").first.click()
    options = page.get_by_role("option")
    options.first.wait_for()
    texts = options.all_inner_texts()
    page.keyboard.press("Escape")
    options.first.wait_for(state="hidden")
    return texts


@pytest.mark.slow
@pytest.mark.parametrize("fault", params([f for f in FAULTS if f.id == "dashboard-path-outside"]))
def test_a_store_outside_the_allowed_folders_is_refused(fault, fenced, browser):
    page = open_page(browser, fenced.proc.url)
    try:
        dismiss_webgl_notice(page)
        page.get_by_text("Data", exact=True).click()
        panel = store_panel(page)
        store_box = control(page, "Store file").locator("input").first
        folders = f"{fenced.allowed.resolve()}, {fenced.more.resolve()}"
        # the list offers the stores inside allowed/, not the link beside them that leads out
        assert store_options(page) == [str(fenced.store), str(fenced.allowed / "copy.sqlite")]
        for path in (fenced.outside / "drives.sqlite", f"{fenced.allowed}/../outside/drives.sqlite",
                     fenced.allowed / "link.sqlite"):
            shown = open_other_store(page, path)
            assert shown.inner_text() == "⚠ " + OUTSIDE.format(path, folders)
            # the store shown stays
            assert store_box.input_value() == str(fenced.store)
            assert panel.locator("xpath=./*[1]").inner_text() == str(fenced.store)
        message = page.get_by_text("⚠ " + OUTSIDE.format(fenced.allowed / "link.sqlite", folders), exact=True).last
        message.scroll_into_view_if_needed()  # the line under Open, where the user is looking
        screenshot(page, f"faults_{fault.id}.png")
        # a store in the other allowed folder opens
        second = fenced.more / "second.sqlite"
        box = control(page, "Other store").locator("input, textarea").first
        box.fill(str(second))
        page.get_by_text(f"Open reads {second}", exact=True).wait_for()
        page.get_by_role("button", name="Open", exact=True).click()
        page.get_by_text(f"Opened {second}: 2 image series", exact=True).wait_for()
        wait_for(lambda: store_box.input_value() == str(second), SERVER_WORK_S, "the store box to show the store opened")
        assert store_options(page) == [str(second)]
        assert fenced.proc.alive()
        assert not any("warning" in line for line in fenced.proc.output), "warned of serving on 127.0.0.1"
    finally:
        page.close()


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("0.0.0.0", 0))
        return s.getsockname()[1]


@pytest.mark.parametrize("fault", params([f for f in FAULTS if f.id == "dashboard-public-host-warning"]))
def test_serving_beyond_this_machine_is_warned_of(fault, tmp_path):
    store = tmp_path / "drives.sqlite"  # missing: the page would say so; the warning does not need it
    proc = subprocess.Popen([sys.executable, "-m", "visloc", "dashboard", "--db", str(store), "--host", "0.0.0.0",
                             "--port", str(free_port())], cwd=REPO, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env={**os.environ, "PYTHONUNBUFFERED": "1"})
    out: list[str] = []
    err: list[str] = []

    def read(stream, lines: list[str]) -> None:
        for line in stream:
            lines.append(line)

    for stream, lines in ((proc.stdout, out), (proc.stderr, err)):
        threading.Thread(target=read, args=(stream, lines), daemon=True).start()
    try:
        url = wait_for(lambda: next((m.group(1) for line in list(out) if (m := URL_LINE.search(line))), None),
                       180, "the URL line")  # Python, numpy, OpenCV and viser import slowly on a busy machine
        port = int(url.rsplit(":", 1)[1])
        warning = wait_for(lambda: next((line for line in list(err) if "warning" in line), None), SERVER_WORK_S,
                           "the warning on stderr")
        assert warning.rstrip("\n") == (
            f"visloc dashboard: warning: serving on 0.0.0.0: anyone who reaches port {port} can open the stores "
            f"under {tmp_path.resolve()}; to look from another machine, keep the default host and use an SSH "
            f"tunnel (ssh -L {port}:localhost:{port} this-machine)")
        assert err == [warning], err  # one line, and nothing else
    finally:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(30)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
