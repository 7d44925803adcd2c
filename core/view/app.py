"""The operator view's HTTP API and page (FastAPI).

One app serves both a running inspection (``feed`` given: the live frame, the current verdict) and
a finished run's results store for review. Everything else (counters, filmstrip, alarms, parts,
CSV) is read from the results store, so the live page and the review page show the same record.
"""
from __future__ import annotations

import asyncio
import io
import re
import secrets
import sqlite3
import time
from pathlib import Path
from typing import Literal
from urllib.parse import urlsplit

import cv2
import numpy as np
from fastapi import FastAPI, HTTPException, Query, Request
from fastapi import Path as FastApiPath
from fastapi.responses import FileResponse, JSONResponse, PlainTextResponse, Response
from fastapi.staticfiles import StaticFiles
from starlette.concurrency import run_in_threadpool
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.middleware.trustedhost import TrustedHostMiddleware

from core.store import ROW_ID_MAX, write_csv
from core.view.feed import LiveFeed, encode_jpeg
from core.view.queries import StoreReader, counters

STATIC = Path(__file__).parent / "static"
VerdictName = Literal["PASS", "REJECT", "ERROR", "FLAG"]


def create_app(results: Path, feed: LiveFeed | None = None, *, token: str | None = None,
               jpeg_quality: int = 80, max_fps: float = 10.0, allowed_hosts: list[str] | None = None) -> FastAPI:
    """``allowed_hosts``: the names the page may be asked for (Host header); on loopback these are the
    loopback names, so that a web page of another site cannot reach the view through DNS rebinding."""
    reader = StoreReader(results)
    app = FastAPI(title="stereo-inspect operator view", docs_url=None, redoc_url=None, openapi_url=None)
    app.mount("/static", StaticFiles(directory=STATIC), name="static")

    @app.middleware("http")
    async def same_origin_writes(request: Request, call_next):
        # A page of another site may make the operator's browser POST here (acknowledging alarms)
        # without asking first; browsers always say where such a request comes from.
        origin = request.headers.get("origin")
        if request.method not in ("GET", "HEAD") and origin and urlsplit(origin).netloc != request.headers.get("host"):
            return JSONResponse({"error": f"cross-site request from {origin} refused"}, status_code=403)
        return await call_next(request)

    if token:
        @app.middleware("http")
        async def require_token(request: Request, call_next):
            given = request.query_params.get("token") or request.cookies.get("view_token") or ""
            auth = request.headers.get("authorization", "")
            if auth.lower().startswith("bearer "):
                given = auth[7:]
            if not secrets.compare_digest(given.encode(), token.encode()):
                return PlainTextResponse("this page needs its access token: open it as /?token=...", status_code=401)
            response = await call_next(request)
            if request.query_params.get("token"):
                response.set_cookie("view_token", token, httponly=True, samesite="strict")
            return response

    if allowed_hosts:
        # added last, so it runs first
        app.add_middleware(TrustedHostMiddleware, allowed_hosts=allowed_hosts)

    def run_or_latest(run: int | None) -> int | None:
        if run is not None:
            return run
        if feed is not None and feed.state == "starting":
            return None  # the store's newest run is still the previous one
        return reader.latest_run()

    @app.get("/", include_in_schema=False)
    def index() -> FileResponse:
        return FileResponse(STATIC / "index.html", headers={"Cache-Control": "no-store"})

    @app.get("/api/state")
    def state(run: int | None = None) -> dict:
        run_id = run_or_latest(run)
        return {
            "mode": "live" if feed is not None else "review",
            "state": feed.state if feed is not None else "finished",
            "recipe": feed.recipe_name if feed is not None else _recipe_name(reader, run_id),
            "run_id": run_id,
            "verdict": _current_verdict(feed, reader, run_id),
            "counters": _counters(feed, reader, run, run_id),
            "fps": round(feed.fps(), 2) if feed is not None else None,
            "frame_seq": feed.seq if feed is not None else None,
            "filmstrip": reader.filmstrip(run_id),
            "alarms": reader.alarms(run_id),
            "master_parts": reader.master_parts(run_id),
            "max_fps": max_fps,
            "time": time.time(),
        }

    @app.get("/api/meta")
    def meta() -> dict:
        return {"runs": reader.runs(), "classes": reader.classes()}

    @app.get("/api/frame.jpg")
    async def frame(after: int = 0, wait: float = Query(2.0, ge=0.0, le=10.0)) -> Response:
        """The newest annotated frame; waits up to ``wait`` s for one newer than ``after`` (long
        poll), so a browser gets frames exactly as fast as it takes them."""
        if feed is None:
            raise HTTPException(404, "no live inspection here (review mode)")
        deadline = time.monotonic() + wait
        while feed.seq <= after and feed.state != "finished" and time.monotonic() < deadline:
            await asyncio.sleep(0.02)
        got = await run_in_threadpool(feed.latest_jpeg, jpeg_quality)
        if got is None:
            return Response(status_code=204)
        seq, data = got
        return Response(data, media_type="image/jpeg", headers={"X-Frame-Seq": str(seq), "Cache-Control": "no-store"})

    @app.get("/api/parts")
    def parts(run: int | None = Query(None, ge=0, le=ROW_ID_MAX), verdict: VerdictName | None = None,
              defect_class: str | None = Query(None, alias="class"),
              page: int = Query(1, ge=1), per_page: int = Query(25, ge=1, le=500)) -> dict:
        return reader.parts(run_or_latest(run), verdict, defect_class, page, per_page)

    @app.get("/api/parts/{part_id}")
    def part(part_id: str) -> dict:
        found = reader.part(part_id)
        if found is None:
            raise HTTPException(404, f"part {part_id} not in {reader.path}")
        found.pop("image_path", None)  # a path on the inspection PC: the browser gets image_url instead
        found["image_url"] = f"/api/parts/{part_id}/image.jpg"
        return found

    @app.get("/api/parts/{part_id}/image.jpg")
    async def part_image(part_id: str, w: int | None = Query(None, ge=16, le=4096)) -> Response:
        data = await run_in_threadpool(_part_jpeg, reader, feed, part_id, jpeg_quality, w)
        if data is None:
            raise HTTPException(404, f"no image kept for part {part_id} (results.save_images)")
        return Response(data, media_type="image/jpeg", headers={"Cache-Control": "max-age=3600"})

    @app.post("/api/alarms/{alarm_id}/ack")
    def acknowledge(alarm_id: int = FastApiPath(ge=0, le=ROW_ID_MAX)) -> dict:
        if not reader.acknowledge(alarm_id):
            raise HTTPException(404, f"no alarm {alarm_id}")
        return {"acknowledged": alarm_id}

    @app.get("/api/export.csv")
    def export(run: int | None = Query(None, ge=0, le=ROW_ID_MAX), verdict: VerdictName | None = None,
               defect_class: str | None = Query(None, alias="class")) -> Response:
        run_id = run_or_latest(run)
        buf = io.StringIO()
        write_csv(reader.csv_rows(run_id, verdict, defect_class), buf)
        name = f"parts-run{run_id or 'all'}{'-' + verdict if verdict else ''}{'-' + defect_class if defect_class else ''}.csv"
        name = re.sub(r"[^A-Za-z0-9_.-]", "_", name)  # the class comes from the URL: keep the header plain ASCII
        return Response(buf.getvalue(), media_type="text/csv",
                        headers={"Content-Disposition": f'attachment; filename="{name}"'})

    # Starlette's class: also the router's own 404 and 405 answer in the same shape
    @app.exception_handler(StarletteHTTPException)
    async def http_error(request: Request, exc: StarletteHTTPException) -> JSONResponse:
        return JSONResponse({"error": exc.detail}, status_code=exc.status_code)

    # the store replaced or damaged while the page is up: said, not a bare "Internal Server Error"
    @app.exception_handler(sqlite3.Error)
    async def store_error(request: Request, exc: sqlite3.Error) -> JSONResponse:
        return JSONResponse({"error": f"{reader.path}: the results store cannot be read ({exc})"}, status_code=503)

    return app


def _recipe_name(reader: StoreReader, run_id: int | None) -> str:
    for run in reader.runs():
        if run["id"] == run_id:
            return run["recipe_name"]
    return ""


def _counters(feed: LiveFeed | None, reader: StoreReader, asked_run: int | None, run_id: int | None) -> dict:
    if feed is not None and asked_run is None:  # the line's own run: counted as it goes
        return counters(*feed.verdict_counts(), reader.alarm_count(run_id))
    return reader.counters(run_id)


def _current_verdict(feed: LiveFeed | None, reader: StoreReader, run_id: int | None) -> dict | None:
    if feed is not None:
        part = feed.latest_part()
        if part is None:
            return None
        return {"status": part.verdict.status.value, "reasons": part.verdict.reasons, "part_id": part.part_id,
                "frame_id": part.frame_id}
    listing = reader.parts(run_id, None, None, 1, 1)["parts"]
    if not listing:
        return None
    last = listing[0]
    return {"status": last["verdict"], "reasons": last["reasons"], "part_id": last["part_id"], "frame_id": last["frame_id"]}


def _part_jpeg(reader: StoreReader, feed: LiveFeed | None, part_id: str, quality: int, width: int | None) -> bytes | None:
    found = reader.part(part_id)
    if found is None:
        return None
    candidates = []
    if found.get("image_path"):
        saved = Path(found["image_path"])
        # the store may have been moved since: its own images/ folder comes second
        candidates += [saved, reader.path.parent / "images" / saved.name]
    for path in candidates:
        if path.is_file():
            if width is None:
                return path.read_bytes()
            image = cv2.imdecode(np.frombuffer(path.read_bytes(), np.uint8), cv2.IMREAD_COLOR)
            if image is not None:
                return encode_jpeg(image, quality, width)
    if feed is not None:
        return feed.reject_jpeg(part_id, quality, width)
    return None
