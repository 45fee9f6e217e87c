"""Screenshots of the rerun web viewer in headless Chromium, one per blueprint tab.

Not a test: a tool to look at what a user sees. It serves a run's recording once with the
rerun web viewer on 127.0.0.1 (after ``rerun analytics disable``), opens it once in headless
Chromium with every host but 127.0.0.1 unresolvable (``--host-resolver-rules``) and saves a
PNG per right-hand tab of the saved layout. The viewer draws into a canvas (no DOM to
click), so each further tab is shown by sending the same blueprint with that tab active to
the running viewer (gRPC, 127.0.0.1). No fixed sleeps: a shot is taken when the viewer has
opened the recording and its picture has stopped changing (two equal captures in a row).

  python -m harness.tools.rerun_screenshots RUN_DIR [--out DIR] [--tabs 0,1,2,3]
  python -m harness.tools.rerun_screenshots --live URL --out DIR   (a running --rerun-live)

Chromium is driven over its DevTools pipe (``--remote-debugging-pipe``: NUL-separated JSON
on file descriptors 3 and 4), so nothing but the viewer listens on a port. Needs a
``chromium`` binary (Debian: ``apt-get install chromium``).
"""

from __future__ import annotations

import argparse
import base64
import contextlib
import functools
import hashlib
import http.server
import json
import os
import shutil
import subprocess
import tempfile
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from can_db.process.argcheck import OneLineParser, number
from can_db.process.parent import die_with_parent
from can_db.transport.server import free_port
from harness.analysis.course import course_geometry, scenario_for
from harness.viz.rerun_live import _wait_for_port, rerun_binary, web_viewer_url
from harness.viz.rerun_log import (
    APPLICATION_ID,
    TAB_NAMES,
    build_blueprint,
    course_bounds,
    partial_label,
    recording_layout,
)

#: PNG name per tab of harness.viz.rerun_log.TAB_NAMES.
TABS = ("vehicle_control", "states_qp", "plant", "timing_bus")
BLOCK_OUTSIDE = "MAP * ~NOTFOUND , EXCLUDE 127.0.0.1"


class Chromium:
    """Headless Chromium driven over the DevTools pipe."""

    def __init__(self, width: int = 1600, height: int = 1000) -> None:
        exe = shutil.which("chromium") or shutil.which("chromium-browser") \
            or shutil.which("google-chrome")
        if exe is None:
            raise SystemExit("no chromium binary found (Debian: apt-get install chromium)")
        self._profile = tempfile.mkdtemp(prefix="rerun-shot-")
        cmd_r, self._cmd_w = os.pipe()
        self._res_r, res_w = os.pipe()

        def child() -> None:
            die_with_parent()
            os.dup2(cmd_r, 3)
            os.dup2(res_w, 4)

        self.proc = subprocess.Popen(
            [exe, "--headless=new", "--no-sandbox", "--remote-debugging-pipe",
             "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
             f"--window-size={width},{height}", f"--host-resolver-rules={BLOCK_OUTSIDE}",
             f"--user-data-dir={self._profile}", "--no-first-run", "about:blank"],
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, close_fds=False,
            preexec_fn=child)
        os.close(cmd_r)
        os.close(res_w)
        self._buf = b""
        self._id = 0
        targets = self.call("Target.getTargets")["targetInfos"]
        page = next(t for t in targets if t["type"] == "page")
        self.session = self.call("Target.attachToTarget", targetId=page["targetId"],
                                 flatten=True)["sessionId"]
        self.call("Page.enable", session=True)
        self.call("Emulation.setDeviceMetricsOverride", session=True, width=width,
                  height=height, deviceScaleFactor=1, mobile=False)

    def call(self, method: str, session: bool = False, **params: Any) -> dict[str, Any]:
        """Send one DevTools command and wait for its result (events are skipped)."""
        self._id += 1
        msg: dict[str, Any] = {"id": self._id, "method": method, "params": params}
        if session:
            msg["sessionId"] = self.session
        os.write(self._cmd_w, json.dumps(msg).encode() + b"\0")
        while True:
            while b"\0" not in self._buf:
                chunk = os.read(self._res_r, 1 << 20)
                if not chunk:
                    raise RuntimeError("chromium closed the DevTools pipe")
                self._buf += chunk
            raw, self._buf = self._buf.split(b"\0", 1)
            reply = json.loads(raw)
            if reply.get("id") == self._id:
                if "error" in reply:
                    raise RuntimeError(f"{method}: {reply['error']}")
                return dict(reply.get("result", {}))

    def capture(self) -> bytes:
        """One PNG of the page as it is drawn (waits for the next frame)."""
        return base64.b64decode(self.call("Page.captureScreenshot", session=True,
                                          format="png")["data"])

    def href(self) -> str:
        """The page's address (the viewer rewrites it when it opens a recording)."""
        res = self.call("Runtime.evaluate", session=True, expression="location.href")
        return str(res.get("result", {}).get("value", ""))

    def settle(self, timeout_s: float, ready: Any = None, differs_from: bytes | None = None
               ) -> tuple[bytes, bool]:
        """Capture until two captures in a row are equal (the viewer draws every frame
        but nothing new any more), ``ready()`` is true and the picture is not
        ``differs_from``; returns (PNG, settled). ``settled`` is False when ``timeout_s``
        ran out (last PNG kept)."""
        end = time.monotonic() + timeout_s
        last, png = b"", b""
        old = hashlib.sha1(differs_from).digest() if differs_from else None
        while time.monotonic() < end:
            try:
                png = self.capture()
                digest = hashlib.sha1(png).digest()
                if digest == last and digest != old and (ready is None or ready()):
                    return png, True
            except RuntimeError:  # the page is between documents while it navigates
                digest = b""
            last = digest
            time.sleep(0.1)
        return png, False

    def screenshot(self, url: str, path: Path, timeout_s: float) -> Path:
        """Open ``url``, wait until the picture settles, save a PNG."""
        self.call("Page.navigate", session=True, url=url)
        png, _ = self.settle(timeout_s, ready=lambda: self.href() != url)
        path.write_bytes(png)
        return path

    def close(self) -> None:
        with contextlib.suppress(RuntimeError, OSError):
            self.call("Browser.close")
        try:
            self.proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            self.proc.kill()
        for fd in (self._cmd_w, self._res_r):
            os.close(fd)
        shutil.rmtree(self._profile, ignore_errors=True)


def _rerun_exe() -> str:
    return rerun_binary()


def serve(files: list[Path]) -> tuple[subprocess.Popen[bytes], str]:
    """A web viewer for ``files`` on 127.0.0.1; returns (process, browser URL)."""
    web, grpc = free_port(), free_port()
    proc = subprocess.Popen(
        [_rerun_exe(), "--serve-web", "--bind", "127.0.0.1", "--port", str(grpc),
         "--web-viewer-port", str(web), *map(str, files)],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, preexec_fn=die_with_parent)
    if not (_wait_for_port(grpc, 30.0) and _wait_for_port(web, 10.0)):
        proc.kill()
        raise RuntimeError("rerun web viewer did not start")
    return proc, web_viewer_url(web, grpc)


class _Files(http.server.SimpleHTTPRequestHandler):
    """Static files for the viewer page (another port: it needs the CORS header)."""

    def end_headers(self) -> None:
        self.send_header("Access-Control-Allow-Origin", "*")
        super().end_headers()

    def log_message(self, format: str, *args: Any) -> None:
        pass


@contextlib.contextmanager
def file_server(root: Path) -> Iterator[str]:
    """``root`` over HTTP on 127.0.0.1 (a thread); yields the base URL. The viewer reads a
    file over HTTP in one go, much faster than through its gRPC proxy."""
    srv = http.server.ThreadingHTTPServer(
        ("127.0.0.1", 0), functools.partial(_Files, directory=str(root)))
    thread = threading.Thread(target=srv.serve_forever, daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{srv.server_address[1]}"
    finally:
        srv.shutdown()
        srv.server_close()


def shoot_run(run_dir: Path, out: Path, timeout_s: float,
              tabs: tuple[int, ...] = tuple(range(len(TABS)))) -> list[Path]:
    """One screenshot per tab (indices into ``TABS``) of ``RUN_DIR/run.rrd``, with the
    layout write_rrd saved: one viewer, one browser page, the tabs switched by blueprint."""
    import rerun.blueprint as rrb

    meta = json.loads((run_dir / "metrics.json").read_text())
    params = dict(meta.get("params") or {})
    geo = course_geometry(scenario_for(meta["scenario"], meta.get("mu"),
                                       meta.get("speed_kmh"), params))
    layout = recording_layout(run_dir / "run.rrd")
    bounds = course_bounds(geo.boundaries, geo.ref_path, geo.cones, driven=layout["driven"])

    def blueprint(tab: int) -> rrb.Blueprint:
        return build_blueprint(bounds, tab, ranges=layout["ranges"], states=layout["states"],
                               note=partial_label(meta), tops=layout["tops"])

    shots: list[Path] = []
    start = time.monotonic()
    with tempfile.TemporaryDirectory() as tmp, file_server(Path(tmp)) as files:
        os.symlink((run_dir / "run.rrd").resolve(), Path(tmp) / "run.rrd")
        # The recording comes over HTTP (fast); the viewer is also connected to its own
        # gRPC proxy, through which each further tab's blueprint is sent (made active).
        viewer, grpc_url = serve([])
        page, proxy = grpc_url.split("?url=", 1)
        url = f"{page}?url={files}/run.rrd&url={proxy}"
        proxy = "rerun+http://" + proxy.split("://", 1)[1]
        browser = Chromium()
        try:
            previous: bytes | None = None
            browser.call("Page.navigate", session=True, url=url)
            for n, tab in enumerate(tabs):
                if n or tab != 0:  # the recording's own layout opens on the first tab
                    blueprint(tab).connect_grpc(APPLICATION_ID, url=proxy, make_active=True,
                                                make_default=False)
                png, settled = browser.settle(timeout_s, ready=lambda: browser.href() != url,
                                              differs_from=previous)
                if not settled:
                    print(f"rerun_screenshots: {TAB_NAMES[tab]!r} still changing after "
                          f"{timeout_s:g} s; saved as it was")
                path = out / f"rerun_{TABS[tab]}.png"
                path.write_bytes(png)
                print(f"{path}  ({time.monotonic() - start:.1f} s)", flush=True)
                shots.append(path)
                previous = png
        finally:
            browser.close()
            viewer.terminate()
            viewer.wait(timeout=10)
    return shots


def _tab_list(text: str) -> tuple[int, ...]:
    """``--tabs``: comma-separated tab indices."""
    wrong = argparse.ArgumentTypeError(f"wants indices 0..{len(TABS) - 1}, e.g. 0,2")
    try:
        tabs = tuple(int(t) for t in text.split(","))
    except ValueError:
        raise wrong from None
    if not tabs or any(not 0 <= t < len(TABS) for t in tabs):
        raise wrong
    return tabs


def main(argv: list[str] | None = None) -> int:
    parser = OneLineParser(prog="python -m harness.tools.rerun_screenshots",
                           description=__doc__)
    parser.add_argument("run_dir", nargs="?", type=Path, help="a run directory with run.rrd")
    parser.add_argument("--live", default=None,
                        help="URL of a running live view (printed by --rerun-live)")
    parser.add_argument("--out", type=Path, default=None,
                        help="where the PNGs go (default: RUN_DIR)")
    parser.add_argument("--timeout-s", type=number(lo=1.0, hi=600.0, unit="s"),
                        default=120.0,
                        help="longest wait for one picture to settle, s (it is taken as "
                             "soon as the viewer has stopped drawing)")
    parser.add_argument("--tabs", type=_tab_list, default=tuple(range(len(TABS))),
                        help=f"tabs to shoot, comma-separated indices into {', '.join(TABS)} "
                             "(default: all)")
    args = parser.parse_args(argv)
    if (args.run_dir is None) == (args.live is None):
        parser.error("give a RUN_DIR or --live URL")
    if args.live is not None and not args.live.startswith("http://127.0.0.1:"):
        parser.error("--live must be an http://127.0.0.1 address")
    out = args.out or args.run_dir
    out.mkdir(parents=True, exist_ok=True)
    subprocess.run([_rerun_exe(), "analytics", "disable"], check=False,
                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, timeout=30)
    if args.live is not None:
        browser = Chromium()
        try:
            shots = [browser.screenshot(args.live, out / "rerun_live.png", args.timeout_s)]
        finally:
            browser.close()
    else:
        if not (args.run_dir / "run.rrd").is_file():
            parser.error(f"{args.run_dir}/run.rrd: no such file")
        shots = shoot_run(args.run_dir, out, args.timeout_s, args.tabs)
        return 0
    for p in shots:
        print(p)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
