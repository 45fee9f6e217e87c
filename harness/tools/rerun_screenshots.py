"""Screenshots of the rerun web viewer in headless Chromium, one per blueprint tab.

Not a test: a tool to look at what a user sees. It serves a run's recording with the rerun
web viewer on 127.0.0.1 (after ``rerun analytics disable``), opens it in headless Chromium
with every host but 127.0.0.1 unresolvable (``--host-resolver-rules``), waits for the viewer
to draw, and saves a PNG. Each right-hand tab ('Vehicle & control', 'Plant states',
'Timing & bus') is shown by serving the recording with a blueprint whose active tab is that
one (the viewer draws into a canvas: there are no DOM elements to click).

  python -m harness.tools.rerun_screenshots RUN_DIR [--out DIR] [--wait-s S]
  python -m harness.tools.rerun_screenshots --live URL --out DIR   (a running --rerun-live)

Chromium is driven over its DevTools pipe (``--remote-debugging-pipe``: NUL-separated JSON
on file descriptors 3 and 4), so nothing but the viewer listens on a port. Needs a
``chromium`` binary (Debian: ``apt-get install chromium``).
"""

from __future__ import annotations

import base64
import contextlib
import json
import os
import shutil
import subprocess
import tempfile
import time
from pathlib import Path
from typing import Any

from can_db.process.argcheck import OneLineParser, number
from can_db.process.parent import die_with_parent
from can_db.transport.server import free_port

TABS = ("vehicle_control", "plant_states", "timing_bus")
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

    def screenshot(self, url: str, path: Path, wait_s: float) -> Path:
        """Open ``url``, wait ``wait_s`` (the viewer compiles and draws), save a PNG."""
        self.call("Page.navigate", session=True, url=url)
        time.sleep(wait_s)
        data = self.call("Page.captureScreenshot", session=True, format="png")["data"]
        path.write_bytes(base64.b64decode(data))
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
    from harness.viz.rerun_live import rerun_binary

    return rerun_binary()


def serve(files: list[Path]) -> tuple[subprocess.Popen[bytes], str]:
    """A web viewer for ``files`` on 127.0.0.1; returns (process, browser URL)."""
    from harness.viz.rerun_live import _wait_for_port, web_viewer_url

    web, grpc = free_port(), free_port()
    proc = subprocess.Popen(
        [_rerun_exe(), "--serve-web", "--bind", "127.0.0.1", "--port", str(grpc),
         "--web-viewer-port", str(web), *map(str, files)],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, preexec_fn=die_with_parent)
    if not (_wait_for_port(grpc, 30.0) and _wait_for_port(web, 10.0)):
        proc.kill()
        raise RuntimeError("rerun web viewer did not start")
    return proc, web_viewer_url(web, grpc)


def shoot_run(run_dir: Path, out: Path, wait_s: float) -> list[Path]:
    """One screenshot per tab of ``RUN_DIR/run.rrd``."""
    from harness.analysis.course import course_geometry, scenario_for
    from harness.viz.rerun_log import APPLICATION_ID, build_blueprint, course_bounds

    meta = json.loads((run_dir / "metrics.json").read_text())
    params = {k: v for k, v in (meta.get("params") or {}).items()}
    geo = course_geometry(scenario_for(meta["scenario"], meta.get("mu"),
                                       meta.get("speed_kmh"), params))
    bounds = course_bounds(geo.boundaries, geo.ref_path, geo.cones)
    shots = []
    browser = Chromium()
    try:
        with tempfile.TemporaryDirectory() as tmp:
            for i, tab in enumerate(TABS):
                rbl = Path(tmp) / f"{tab}.rbl"
                build_blueprint(bounds, active_tab=i).save(APPLICATION_ID, rbl)
                viewer, url = serve([run_dir / "run.rrd", rbl])
                try:
                    shots.append(browser.screenshot(url, out / f"rerun_{tab}.png", wait_s))
                finally:
                    viewer.terminate()
                    viewer.wait(timeout=10)
    finally:
        browser.close()
    return shots


def main(argv: list[str] | None = None) -> int:
    parser = OneLineParser(prog="python -m harness.tools.rerun_screenshots",
                           description=__doc__)
    parser.add_argument("run_dir", nargs="?", type=Path, help="a run directory with run.rrd")
    parser.add_argument("--live", default=None,
                        help="URL of a running live view (printed by --rerun-live)")
    parser.add_argument("--out", type=Path, default=None,
                        help="where the PNGs go (default: RUN_DIR)")
    parser.add_argument("--wait-s", type=number(lo=1.0, hi=600.0, unit="s"), default=75.0,
                        help="wait after opening, s: the WebAssembly viewer compiles, then "
                             "ingests the recording; plots drawn before it has all the data "
                             "show stray lines (≈ 30 s was too short on a loaded 2-core "
                             "machine)")
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
            shots = [browser.screenshot(args.live, out / "rerun_live.png", args.wait_s)]
        finally:
            browser.close()
    else:
        if not (args.run_dir / "run.rrd").is_file():
            parser.error(f"{args.run_dir}/run.rrd: no such file")
        shots = shoot_run(args.run_dir, out, args.wait_s)
    for p in shots:
        print(p)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
