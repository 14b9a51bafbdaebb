"""Our recordings and live view in a real viewer: the Lichtblick web build (``../shared/viewers/lichtblick-web``)
served on loopback and driven in headless Chromium by Playwright, for the tests and the docs' screenshots
(``tests/test_viewer.py``; a test-time helper like ``netns.py``: nothing at run time needs a browser).

    with Lichtblick(viewer_dir, files_dir) as lb:
        page = lb.open_recording("run.mcap")      # ?ds=remote-file&ds.url=...
        lb.import_layout(page, "docs/lichtblick-layout.json")
        problems = lb.problems(page)

One static server answers both the viewer's files and the recordings (``/files/...``), with ``Range`` and
``Access-Control-Allow-Origin`` (the viewer reads an MCAP in ranges). Playwright and Chromium are test-time
dependencies (``pip install -e '.[test]'``, Debian's ``chromium``): nothing at run time needs them.
"""

from __future__ import annotations

import functools
import os
import re
import shutil
import threading
from http import HTTPStatus
from http.server import SimpleHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

CHROMIUM_ARGS = ["--no-sandbox", "--use-gl=swiftshader", "--enable-unsafe-swiftshader", "--disable-background-networking",
                 "--disable-component-update", "--disable-sync", "--no-first-run", "--disable-dev-shm-usage"]
"""Headless Chromium without a GPU (the 3D panel renders on SwiftShader) and without calls home."""


def viewer_dir() -> Path:
    """The web build: $LICHTBLICK_DIR, else ``shared/viewers/lichtblick-web`` beside the checkout or in /work."""
    if os.environ.get("LICHTBLICK_DIR"):
        return Path(os.environ["LICHTBLICK_DIR"])
    here = Path(__file__).resolve().parents[1]
    for root in (here.parent, Path("/work")):
        if (root / "shared" / "viewers" / "lichtblick-web" / "index.html").is_file():
            return root / "shared" / "viewers" / "lichtblick-web"
    raise FileNotFoundError("no Lichtblick web build: set LICHTBLICK_DIR (../shared/viewers/lichtblick-web)")


def chromium_path() -> str | None:
    """Debian's chromium (or $CHROMIUM), None when there is none."""
    return os.environ.get("CHROMIUM") or shutil.which("chromium") or shutil.which("chromium-browser")


class _Handler(SimpleHTTPRequestHandler):
    """Static files with single-range ``Range`` requests and CORS; ``/files/...`` from the files folder."""

    files_dir: Path = Path(".")

    def log_message(self, *args) -> None:  # quiet: a test prints what failed, not every request
        pass

    def translate_path(self, path: str) -> str:
        clean = path.split("?", 1)[0].split("#", 1)[0]
        if clean.startswith("/files/"):
            rel = Path(clean[len("/files/"):])
            if ".." in rel.parts:
                return str(self.files_dir / "__nothing__")
            return str(self.files_dir / rel)
        return super().translate_path(path)

    def end_headers(self) -> None:
        self.send_header("Access-Control-Allow-Origin", "*")
        self.send_header("Access-Control-Expose-Headers", "Content-Length, Content-Range, Accept-Ranges")
        self.send_header("Accept-Ranges", "bytes")
        super().end_headers()

    def do_OPTIONS(self) -> None:
        self.send_response(HTTPStatus.NO_CONTENT)
        self.send_header("Access-Control-Allow-Headers", "Range")
        self.send_header("Access-Control-Allow-Methods", "GET, HEAD, OPTIONS")
        self.end_headers()

    def send_head(self):
        m = re.fullmatch(r"bytes=(\d*)-(\d*)", self.headers.get("Range", ""))
        path = Path(self.translate_path(self.path))
        if m is None or not path.is_file():
            return super().send_head()
        size = path.stat().st_size
        start = int(m[1]) if m[1] else max(0, size - int(m[2] or 0))
        end = min(int(m[2]), size - 1) if m[1] and m[2] else size - 1
        if start >= size or start > end:
            self.send_error(HTTPStatus.REQUESTED_RANGE_NOT_SATISFIABLE)
            return None
        f = open(path, "rb")
        f.seek(start)
        self.send_response(HTTPStatus.PARTIAL_CONTENT)
        self.send_header("Content-Type", self.guess_type(str(path)))
        self.send_header("Content-Range", f"bytes {start}-{end}/{size}")
        self.send_header("Content-Length", str(end - start + 1))
        self.end_headers()
        return _Slice(f, end - start + 1)


class _Slice:
    """The part of a file a range asks for, as ``copyfile`` reads it."""

    def __init__(self, f, n: int):
        self.f, self.left = f, n

    def read(self, size: int = -1) -> bytes:
        size = self.left if size < 0 else min(size, self.left)
        data = self.f.read(size)
        self.left -= len(data)
        return data

    def close(self) -> None:
        self.f.close()


class FileServer:
    """The viewer's files and ``/files/`` on 127.0.0.1 (a free port), served on a thread."""

    def __init__(self, viewer_dir: Path, files_dir: Path):
        handler = type("Handler", (_Handler,), {"files_dir": Path(files_dir)})
        self.httpd = ThreadingHTTPServer(("127.0.0.1", 0), functools.partial(handler, directory=str(viewer_dir)))
        self.url = f"http://127.0.0.1:{self.httpd.server_address[1]}"
        self._thread = threading.Thread(target=self.httpd.serve_forever, name="viewer-http", daemon=True)

    def __enter__(self) -> "FileServer":
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self.httpd.shutdown()
        self.httpd.server_close()


PROBLEM_MARKERS = ("Player problem", "Error in topic", "Failed to parse", "Unsupported", "Invalid")
"""Console text the viewer prints when it cannot read a topic or a source (besides its Problems tab)."""


class Viewer:
    """Headless Chromium on the served viewer: open a source, import a layout, read the problems, the topics
    and the 3D panel's pixels. A context manager (the browser and the server end with it)."""

    def __init__(self, files_dir: Path, viewport: tuple[int, int] = (1600, 1000)):
        self.files_dir, self.viewport = Path(files_dir), viewport
        self.console: list[str] = []

    def __enter__(self) -> "Viewer":
        from playwright.sync_api import sync_playwright

        exe = chromium_path()
        if exe is None:
            raise FileNotFoundError("no chromium: apt-get install -y chromium (or set CHROMIUM)")
        self.server = FileServer(viewer_dir(), self.files_dir).__enter__()
        self._pw = sync_playwright().start()
        self.browser = self._pw.chromium.launch(executable_path=exe, args=CHROMIUM_ARGS)
        self.page = self.browser.new_page(viewport={"width": self.viewport[0], "height": self.viewport[1]})
        self.page.on("console", lambda m: self.console.append(f"{m.type}: {m.text}"))
        self.page.on("pageerror", lambda e: self.console.append(f"pageerror: {e}"))
        # "Import from file…" asks the File System Access API for a file: hand it the layout we set
        self.page.add_init_script("""window.showOpenFilePicker = async () => [{kind: 'file', name: 'layout.json',
            getFile: async () => new File([window.__layout || ''], window.__layoutName || 'layout.json',
                                           {type: 'application/json'})}];""")
        return self

    def __exit__(self, *exc) -> None:
        self.browser.close()
        self._pw.stop()
        self.server.__exit__(*exc)

    def open_recording(self, name: str, at_ns: int | None = None) -> None:
        """``/files/<name>`` as a remote file, the playhead at ``at_ns`` (UNIX ns; None: the start)."""
        url = f"{self.server.url}/?ds=remote-file&ds.url={self.server.url}/files/{name}"
        if at_ns is not None:
            url += "&time=" + _iso(at_ns)
        self.page.goto(url)

    def open_live(self, ws_url: str) -> None:
        """A live Foxglove WebSocket server, e.g. ``ws://127.0.0.1:8765``."""
        self.page.goto(f"{self.server.url}/?ds=foxglove-websocket&ds.url={ws_url}")

    def import_layout(self, path: Path) -> None:
        """Layouts tab -> Import from file…: the viewer's own import, with ``path``'s text."""
        self.page.evaluate("([text, name]) => { window.__layout = text; window.__layoutName = name; }",
                           [Path(path).read_text(), Path(path).name])
        self.page.get_by_text("Layouts", exact=True).click()
        self.page.get_by_text(re.compile("^Import from file")).click()
        self.page.get_by_text(Path(path).stem, exact=True).first.wait_for(timeout=15_000)

    def problems(self) -> list[str]:
        """What the viewer reports: its Problems tab's entries and problem lines in its console."""
        self.page.get_by_role("tab", name=re.compile("^Problems")).click()  # "Problems 1": a badge with the count
        self.page.wait_for_timeout(300)
        text = self._sidebar().inner_text().strip()
        tab = [] if text in ("", "No problems found") else [f"Problems tab: {text}"]
        return tab + [c for c in self.console if any(m in c for m in PROBLEM_MARKERS)]

    def topics(self) -> list[str]:
        """The Topics tab's topic names (its list draws only the rows in view: a tall window for the reading)."""
        self.page.set_viewport_size({"width": self.viewport[0], "height": 4000})
        try:
            self.page.get_by_text("Topics", exact=True).click()
            self.page.wait_for_timeout(500)
            lines = self._sidebar().inner_text().splitlines()
        finally:
            self.page.set_viewport_size({"width": self.viewport[0], "height": self.viewport[1]})
        return [line for line in lines if line.startswith("/")]

    def _sidebar(self):
        return self.page.locator("[data-testid=sidebar-left] [class*=tabContent]").first

    def panel_3d(self, save: Path | None = None):
        """The 3D panel's pixels (its canvas, the largest on the page) as an RGB array; ``save``: the whole page."""
        import io

        import numpy as np
        from PIL import Image

        shot = self.page.screenshot(path=str(save) if save else None)
        canvases = [c.bounding_box() for c in self.page.locator("canvas").all()]
        box = max((b for b in canvases if b), key=lambda b: b["width"] * b["height"])
        img = np.asarray(Image.open(io.BytesIO(shot)).convert("RGB"))
        x0, y0 = int(box["x"]), int(box["y"])
        return img[y0:y0 + int(box["height"]), x0:x0 + int(box["width"])]


def _iso(ns: int) -> str:
    import datetime

    t = datetime.datetime.fromtimestamp(ns / 1e9, tz=datetime.timezone.utc)
    return t.strftime("%Y-%m-%dT%H:%M:%S.%f")[:-3] + "Z"
