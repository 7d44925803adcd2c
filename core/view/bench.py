"""What watching costs the line: the same run with no browser, with browsers pulling every frame, and
with a browser that stopped reading. Clients behave like the page: one frame request at a time
(long-polled), and the state every half second."""
from __future__ import annotations

import socket
import threading
import time
import urllib.request
from dataclasses import dataclass

from core import engine
from core.recipe import LoadedRecipe
from core.view.app import create_app
from core.view.feed import LiveFeed
from core.view.server import ViewServer


class PageLikeClient(threading.Thread):
    def __init__(self, base: str):
        super().__init__(daemon=True)
        self.base, self.frames, self.bytes = base, 0, 0
        self.stop = threading.Event()

    def run(self) -> None:
        seq, next_state = 0, 0.0
        while not self.stop.is_set():
            try:
                if time.monotonic() >= next_state:
                    with urllib.request.urlopen(self.base + "api/state", timeout=10) as r:
                        r.read()
                    next_state = time.monotonic() + 0.5
                with urllib.request.urlopen(f"{self.base}api/frame.jpg?after={seq}&wait=0.5", timeout=10) as r:
                    body = r.read()
                    if r.status == 200:
                        new = int(r.headers["X-Frame-Seq"])
                        if new != seq:
                            self.frames += 1
                            self.bytes += len(body)
                        seq = new
            except OSError:
                time.sleep(0.1)


class StalledClient:
    """Asks for many frames on one connection and never reads an answer."""

    def __init__(self, host: str, port: int):
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        # a small receive window before connecting, so the server's sends back up quickly
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        self.sock.connect((host, port))
        request = f"GET /api/frame.jpg?wait=0 HTTP/1.1\r\nHost: {host}:{port}\r\n\r\n".encode()
        self.sock.sendall(request * 500)

    def close(self) -> None:
        self.sock.close()


@dataclass
class ViewBenchRow:
    label: str
    fps: float
    frames: int
    frames_to_browsers: int
    encodes: int


def run_config(loaded: LoadedRecipe, label: str, browsers: int, stalled: bool, frames: int, host: str, port: int,
               device: str) -> ViewBenchRow:
    feed = LiveFeed()
    settings = loaded.recipe.view
    server = ViewServer(create_app(loaded.resolve(loaded.recipe.results.path), feed,
                                   jpeg_quality=settings.jpeg_quality, max_fps=settings.max_fps), host, port).start()
    base = server.url
    clients = [PageLikeClient(base) for _ in range(browsers)]
    blocker = None
    try:
        blocker = StalledClient(host, port) if stalled else None
        for c in clients:
            c.start()
        summary = engine.run(loaded, on_part=feed.part, on_start=lambda _: feed.started(loaded.recipe.name),
                             device=device, max_frames=frames)
    finally:
        for c in clients:
            c.stop.set()
        for c in clients:
            c.join(timeout=15)
        if blocker is not None:
            blocker.close()
        server.stop()
    return ViewBenchRow(label, summary.fps, summary.frames, sum(c.frames for c in clients), feed.encodes)


def markdown(rows: list[ViewBenchRow]) -> str:
    base = rows[0].fps or 1.0
    lines = ["| configuration | loop frames/s | vs. no browser | frames | frames sent to browsers | frames encoded |",
             "|---|---|---|---|---|---|"]
    lines += [f"| {r.label} | {r.fps:.2f} | {r.fps / base:.2f} | {r.frames} | {r.frames_to_browsers} | {r.encodes} |" for r in rows]
    return "\n".join(lines)
