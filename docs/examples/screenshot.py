"""A screenshot of a recording as the web viewer draws it, taken in headless Chromium.

    python docs/examples/screenshot.py out.rrd shot.png [--panel map] [--wait-s 40]

It serves the recording with ``rerun --serve-web`` on loopback, opens the viewer in
headless Chromium (software WebGL: no GPU, no display), waits for it to draw, and takes
a PNG through the Chrome DevTools Protocol (``Page.captureScreenshot``; the whole window,
or with ``--panel map`` the map panel of the recording's layout: the second of its four
columns, 3:3:2:2). Nothing but the standard library: the protocol's WebSocket is the few
lines of RFC 6455 a client needs. It needs ``rerun`` (installed with ``rerun-sdk``) and
Chromium (Debian: ``apt-get install chromium``); docs/viewing.md says how the screenshots
in docs/img/ were taken. Without internet access the map has no OpenStreetMap tiles:
what the recording draws shows on a blank background.
"""

from __future__ import annotations

import argparse
import base64
import json
import os
import shutil
import socket
import struct
import subprocess
import sys
import tempfile
import time
import urllib.parse
import urllib.request
from pathlib import Path

WINDOW = (1600, 900)
MAP_COLUMN = (3 / 10, 6 / 10)  # the map panel's share of the width: columns 3:3:2:2, the second
CHROMIUM_FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
                  "--disable-component-update", "--disable-sync", "--no-first-run",
                  "--enable-unsafe-swiftshader", "--use-angle=swiftshader"]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_http(url: str, timeout: float) -> bytes:
    deadline = time.monotonic() + timeout
    while True:
        try:
            with urllib.request.urlopen(url, timeout=2) as r:
                return r.read()
        except OSError:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.2)


class WebSocket:
    """A client WebSocket (RFC 6455): text frames out (masked), whole messages in."""

    def __init__(self, url: str):
        u = urllib.parse.urlsplit(url)
        self.sock = socket.create_connection((u.hostname, u.port), timeout=60)
        key = base64.b64encode(os.urandom(16)).decode()
        self.sock.sendall((f"GET {u.path} HTTP/1.1\r\nHost: {u.netloc}\r\nUpgrade: websocket\r\n"
                           f"Connection: Upgrade\r\nSec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n\r\n"
                           ).encode())
        head = b""
        while b"\r\n\r\n" not in head:
            head += self.sock.recv(1)
        if b" 101 " not in head.split(b"\r\n", 1)[0]:
            raise OSError(f"WebSocket handshake refused: {head[:200]!r}")

    def _read(self, n: int) -> bytes:
        out = b""
        while len(out) < n:
            chunk = self.sock.recv(n - len(out))
            if not chunk:
                raise OSError("WebSocket closed")
            out += chunk
        return out

    def send(self, text: str) -> None:
        data, mask = text.encode(), os.urandom(4)
        n = len(data)
        head = bytes([0x81]) + (bytes([0x80 | n]) if n < 126 else
                                bytes([0x80 | 126]) + struct.pack(">H", n) if n < 65536 else
                                bytes([0x80 | 127]) + struct.pack(">Q", n))
        self.sock.sendall(head + mask + bytes(b ^ mask[i % 4] for i, b in enumerate(data)))

    def recv(self) -> str:
        message = b""
        while True:
            b0, b1 = self._read(2)
            n = b1 & 0x7F
            if n == 126:
                n = struct.unpack(">H", self._read(2))[0]
            elif n == 127:
                n = struct.unpack(">Q", self._read(8))[0]
            payload = self._read(n)
            if b0 & 0x0F in (0x1, 0x0):  # text, continuation
                message += payload
                if b0 & 0x80:
                    return message.decode()

    def call(self, ident: int, method: str, **params) -> dict:
        self.send(json.dumps({"id": ident, "method": method, "params": params}))
        while True:
            reply = json.loads(self.recv())
            if reply.get("id") == ident:
                if "error" in reply:
                    raise OSError(f"{method}: {reply['error']}")
                return reply["result"]


def screenshot(rrd: Path, out: Path, panel: str | None, wait_s: float) -> None:
    rerun = shutil.which("rerun") or str(Path(sys.executable).with_name("rerun"))
    chromium = shutil.which("chromium") or shutil.which("chromium-browser") or shutil.which("google-chrome")
    if chromium is None:
        sys.exit("screenshot: no Chromium found (Debian: apt-get install chromium)")
    web, grpc, debug = free_port(), free_port(), free_port()
    procs = []
    with tempfile.TemporaryDirectory(ignore_cleanup_errors=True) as profile:
        try:
            procs.append(subprocess.Popen([rerun, "--serve-web", "--bind", "127.0.0.1", "--web-viewer-port", str(web),
                                           "--port", str(grpc), str(rrd)], stdout=subprocess.DEVNULL,
                                          stderr=subprocess.DEVNULL))
            wait_http(f"http://127.0.0.1:{web}/", 30)
            source = urllib.parse.quote(f"rerun+http://127.0.0.1:{grpc}/proxy", safe="")
            procs.append(subprocess.Popen([chromium, *CHROMIUM_FLAGS, f"--user-data-dir={profile}",
                                           f"--window-size={WINDOW[0]},{WINDOW[1]}",
                                           f"--remote-debugging-port={debug}",
                                           f"http://127.0.0.1:{web}/?url={source}"],
                                          stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))
            pages = json.loads(wait_http(f"http://127.0.0.1:{debug}/json/list", 30))
            ws = WebSocket(next(p for p in pages if p.get("type") == "page")["webSocketDebuggerUrl"])
            time.sleep(wait_s)  # the viewer's WebAssembly compiles, loads the file and draws (software GL)
            params: dict = {"format": "png"}
            if panel == "map":
                view = ws.call(2, "Page.getLayoutMetrics")["cssLayoutViewport"]  # the window less its frame
                x0, x1 = (round(f * view["clientWidth"]) for f in MAP_COLUMN)
                params["clip"] = {"x": x0, "y": 0, "width": x1 - x0, "height": view["clientHeight"], "scale": 1}
            out.write_bytes(base64.b64decode(ws.call(1, "Page.captureScreenshot", **params)["data"]))
        finally:
            for p in reversed(procs):
                p.terminate()
                try:
                    p.wait(10)
                except subprocess.TimeoutExpired:
                    p.kill()
                    p.wait()


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("rrd", type=Path, help="the recording")
    ap.add_argument("png", type=Path, help="where the screenshot goes")
    ap.add_argument("--panel", choices=("map",), help="only this panel of the layout (default: the whole window)")
    ap.add_argument("--wait-s", type=float, default=40.0, help="seconds the viewer is given to draw (default 40)")
    args = ap.parse_args()
    screenshot(args.rrd, args.png, args.panel, args.wait_s)
    print(f"{args.png}: {args.png.stat().st_size} bytes")
    return 0


if __name__ == "__main__":
    sys.exit(main())
