"""Serving the operator view with uvicorn in a background thread, beside the inspection."""
from __future__ import annotations

import ipaddress
import socket
import threading
import time

import uvicorn


class ViewError(Exception):
    """The page cannot be served (port taken, bad address); the message says which flag or key to change."""


def is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def allowed_hosts(host: str) -> list[str] | None:
    """Host header names to accept: on loopback only the loopback names (against DNS rebinding);
    on a network address the name the line uses for the PC is not known here, so any."""
    return ["127.0.0.1", "localhost", "[::1]", "::1"] if is_loopback(host) else None


def exposure_warning(host: str, token: str | None) -> str | None:
    if is_loopback(host):
        return None
    if token:
        return f"view: serving on {host}, reachable from the network; the page asks for its token"
    return (f"view: serving on {host} WITHOUT AUTHENTICATION: anyone on the network can see the line and "
            "acknowledge alarms (set view.token or --token, or keep the default 127.0.0.1)")


def check_port(host: str, port: int) -> None:
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    with socket.socket(family, socket.SOCK_STREAM) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind((host, port))
        except OSError as exc:
            raise ViewError(f"view: cannot serve on {host}:{port}: {exc.strerror or exc} (choose another --port or view.port)") from exc


class ViewServer:
    def __init__(self, app, host: str, port: int):
        self.host, self.port = host, port
        check_port(host, port)
        config = uvicorn.Config(app, host=host, port=port, log_level="warning", access_log=False, lifespan="off")
        self._server = uvicorn.Server(config)
        self._thread = threading.Thread(target=self._server.run, name="operator-view", daemon=True)

    @property
    def url(self) -> str:
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"http://{host}:{self.port}/"

    def start(self, timeout_s: float = 10.0) -> ViewServer:
        self._thread.start()
        deadline = time.monotonic() + timeout_s
        while not self._server.started:
            if not self._thread.is_alive() or time.monotonic() > deadline:
                raise ViewError(f"view: the web server did not start on {self.host}:{self.port}")
            time.sleep(0.02)
        return self

    def stop(self) -> None:
        self._server.should_exit = True
        self._thread.join(timeout=5.0)
