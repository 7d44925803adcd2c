"""The operator view's HTTP API over real results stores written by real runs (FastAPI's test client)."""
from __future__ import annotations

import csv
import io
import socket
import threading
import time
import urllib.request

import cv2
import numpy as np
import pytest
import stereo_inspect_fixed_roi
from conftest import write_recipe
from fastapi.testclient import TestClient
from test_engine import RECIPE

from core import engine
from core.recipe import load_recipe
from core.registry import Registry, make_manager
from core.store import ResultsStore
from core.types import Alarm, OutputEvent
from core.view.app import create_app
from core.view.feed import LiveFeed
from core.view.queries import StoreReader, counters
from core.view.server import ViewServer, allowed_hosts, exposure_warning, is_loopback
from drivers.plc_sim import free_port

PITS = [0.0, 6.0, 0.0, 6.0, 0.0]  # frames 1 and 3 have a 6 mm pit: REJECT; frame 4 loses its right image: ERROR


def _run(tmp_path, plane_sequence, save_images="rejected", on_part=None, pits=PITS, break_frame=4):
    info = plane_sequence(pits)
    if break_frame is not None:
        (info["folder"] / "right" / f"{break_frame:06d}.png").unlink()
    registry = Registry(make_manager((stereo_inspect_fixed_roi,)))
    text = RECIPE.format(box=info["box"], output="log").replace("save_images: rejected", f"save_images: {save_images}")
    loaded = load_recipe(write_recipe(tmp_path / "r.yaml", text), registry=registry)
    summary = engine.run(loaded, registry=registry, device="cpu", on_part=on_part)
    return tmp_path / "results", summary


@pytest.fixture
def results(tmp_path, plane_sequence):
    folder, summary = _run(tmp_path, plane_sequence)
    store = ResultsStore(folder)
    store.record_events(summary.run_id, [Alarm("modbus", "PLC 127.0.0.1:5020 unreachable", time.time(), "R1-000003")])
    store.close()
    return folder


def test_review_state_counts_verdict_filmstrip_and_alarms(results):
    state = TestClient(create_app(results)).get("/api/state").json()
    assert state["mode"] == "review" and state["recipe"] == "engine-test" and state["run_id"] == 1
    c = state["counters"]
    assert (c["parts"], c["passed"], c["rejected"], c["errors"]) == (5, 2, 2, 1)
    assert c["yield_percent"] == 40.0 and c["rejects_per_class"] == {"pit": 2}
    assert state["verdict"]["part_id"] == "R1-000004" and state["verdict"]["status"] == "ERROR"
    # newest first, rejects and errors only
    assert [(p["part_id"], p["verdict"]) for p in state["filmstrip"]] == [
        ("R1-000004", "ERROR"), ("R1-000003", "REJECT"), ("R1-000001", "REJECT")]
    assert state["filmstrip"][1]["classes"] == ["pit"]
    assert [a["message"] for a in state["alarms"]] == ["PLC 127.0.0.1:5020 unreachable"]


def test_the_runs_master_part_check_is_in_the_state(results):
    client = TestClient(create_app(results))
    assert client.get("/api/state").json()["master_parts"] is None  # the recipe named none
    store = ResultsStore(results)
    checked = store.start_run("r", "h", "r.yaml", None, {}, ["log"])
    store.record_events(checked, [OutputEvent("verify", None, "master parts", "delivered", time.time(),
                                              "master parts m: 4 inspected, 3 of 3 defective ones rejected")])
    refused = store.start_run("r", "h", "r.yaml", None, {}, ["log"])
    store.record_events(refused, [Alarm("verify", "2 master parts with a defect beyond a limit passed", time.time(),
                                        None, "verify")])
    store.close()
    assert client.get(f"/api/state?run={checked}").json()["master_parts"] == {
        "started": True, "text": "master parts m: 4 inspected, 3 of 3 defective ones rejected"}
    assert client.get(f"/api/state?run={refused}").json()["master_parts"] == {
        "started": False, "text": "2 master parts with a defect beyond a limit passed"}


@pytest.mark.parametrize("method, url", [("get", "/api/parts?run=99999999999999999999"), ("get", "/api/parts?run=-1"),
                                         ("get", "/api/export.csv?run=99999999999999999999"),
                                         ("post", "/api/alarms/99999999999999999999/ack")])
def test_an_id_beyond_the_stores_integers_is_a_bad_request_not_a_server_error(results, method, url):
    # SQLite's integers end at 2**63 - 1: a larger one raised OverflowError inside the query (a 500)
    response = getattr(TestClient(create_app(results), raise_server_exceptions=False), method)(url)
    assert response.status_code == 422


def test_parts_filter_by_verdict_and_class_and_page(results):
    client = TestClient(create_app(results))
    rejected = client.get("/api/parts", params={"verdict": "REJECT"}).json()
    assert rejected["total"] == 2 and {p["part_id"] for p in rejected["parts"]} == {"R1-000001", "R1-000003"}
    assert client.get("/api/parts", params={"class": "pit"}).json()["total"] == 4  # every frame with a box
    assert client.get("/api/parts", params={"class": "scratch"}).json()["total"] == 0
    pages = [client.get("/api/parts", params={"per_page": 2, "page": n}).json() for n in (1, 2, 3)]
    assert [len(p["parts"]) for p in pages] == [2, 2, 1] and pages[0]["total"] == 5
    ids = [p["part_id"] for page in pages for p in page["parts"]]
    assert ids == [f"R1-{i:06d}" for i in (4, 3, 2, 1, 0)]
    assert client.get("/api/parts", params={"verdict": "MAYBE"}).status_code == 422
    # a page past every row SQLite can number is empty, not an overflow in the query (a 500)
    far = client.get("/api/parts", params={"per_page": 500, "page": 10**20})
    assert far.status_code == 200 and far.json()["parts"] == [] and far.json()["total"] == 5


def test_a_store_damaged_while_the_page_is_up_is_named_not_a_bare_500(results):
    client = TestClient(create_app(results), raise_server_exceptions=False)
    assert client.get("/api/state").status_code == 200
    for path in results.glob("results.db*"):
        path.unlink()
    (results / "results.db").write_bytes(b"not a database" * 100)
    for url in ("/api/state", "/api/parts", "/api/meta"):
        answer = client.get(url)
        assert answer.status_code == 503 and answer.json()["error"] == (
            f"{results / 'results.db'}: the results store cannot be read (file is not a database)"), url


def test_part_detail_names_the_rule_and_serves_its_image(results):
    client = TestClient(create_app(results))
    part = client.get("/api/parts/R1-000001").json()
    assert part["verdict"] == "REJECT" and part["reasons"] and "deviation_mm" in part["reasons"][0]
    (defect,) = part["defects"]
    assert defect["class"] == "pit" and defect["verdict"] == "REJECT" and defect["deviation_mm"] > 1.5
    # measured from the images, with the uncertainty the decision used: a 6 mm spherical cap, whose region
    # spans millimetres of depth (the uncertainty counts that bowl), still proven beyond the 1.5 mm limit
    assert defect["depth_method"] == "surface" and 0 < defect["deviation_sigma_mm"] < 1.5
    assert defect["deviation_mm"] - 2 * defect["deviation_sigma_mm"] > 1.5
    # and what that uncertainty is made of, its parts' variances adding up to it
    assert defect["uncertainty"][0]["kind"] == "surface"
    assert sum(p["variance_mm2"] for p in defect["uncertainty"]) == pytest.approx(defect["deviation_sigma_mm"] ** 2)
    assert part["output_events"] and part["output_events"][0]["output"] == "log"
    full = client.get(part["image_url"])
    assert full.status_code == 200 and full.headers["content-type"] == "image/jpeg"
    image = cv2.imdecode(np.frombuffer(full.content, np.uint8), cv2.IMREAD_COLOR)
    assert image.shape[:2] == (192, 320)
    thumb = cv2.imdecode(np.frombuffer(client.get(part["image_url"], params={"w": 160}).content, np.uint8), cv2.IMREAD_COLOR)
    assert thumb.shape[:2] == (96, 160)
    missing = client.get("/api/parts/R9-000000")
    assert missing.status_code == 404 and "R9-000000" in missing.json()["error"]
    # a passed part keeps no image under save_images: rejected
    assert client.get("/api/parts/R1-000000/image.jpg").status_code == 404


def test_alarm_acknowledged_is_stored_and_leaves_the_page(results):
    client = TestClient(create_app(results))
    (alarm,) = client.get("/api/state").json()["alarms"]
    assert client.post(f"/api/alarms/{alarm['id']}/ack").status_code == 200
    assert client.get("/api/state").json()["alarms"] == []
    import sqlite3

    assert sqlite3.connect(results / "results.db").execute("SELECT acknowledged FROM alarms").fetchone()[0] == 1
    assert client.post("/api/alarms/999/ack").status_code == 404


def test_runs_in_progress_show_their_parts(results):
    import sqlite3

    with sqlite3.connect(results / "results.db") as db:  # as while the run is still going
        db.execute("UPDATE runs SET parts = 0, finished = NULL")
    (run,) = TestClient(create_app(results)).get("/api/meta").json()["runs"]
    assert run["parts"] == 5 and run["finished"] is None


def test_another_site_cannot_acknowledge_or_rebind(results):
    client = TestClient(create_app(results, allowed_hosts=allowed_hosts("127.0.0.1")), base_url="http://127.0.0.1:8080")
    (alarm,) = client.get("/api/state").json()["alarms"]
    refused = client.post(f"/api/alarms/{alarm['id']}/ack", headers={"Origin": "http://evil.example"})
    assert refused.status_code == 403 and "evil.example" in refused.json()["error"]
    assert client.get("/api/state").json()["alarms"]  # still open
    # the page's own origin may
    assert client.post(f"/api/alarms/{alarm['id']}/ack", headers={"Origin": "http://127.0.0.1:8080"}).status_code == 200
    # a rebound name reaching the loopback server is refused before anything is read
    assert client.get("/api/state", headers={"Host": "evil.example:8080"}).status_code == 400
    assert allowed_hosts("0.0.0.0") is None


def test_errors_have_one_shape_and_filenames_stay_ascii(results):
    client = TestClient(create_app(results))
    assert client.get("/api/nothing-here").json() == {"error": "Not Found"}
    assert client.put("/api/state").status_code == 405 and "error" in client.put("/api/state").json()
    odd = client.get("/api/export.csv", params={"class": 'ü"x'})
    assert odd.status_code == 200 and odd.headers["content-disposition"] == 'attachment; filename="parts-run1-__x.csv"'
    assert "image_path" not in client.get("/api/parts/R1-000001").json()


def test_csv_export_follows_the_filters(results):
    client = TestClient(create_app(results))
    response = client.get("/api/export.csv", params={"verdict": "REJECT"})
    assert response.status_code == 200 and "attachment" in response.headers["content-disposition"]
    rows = list(csv.DictReader(io.StringIO(response.text)))
    assert [r["part_id"] for r in rows] == ["R1-000001", "R1-000003"]
    assert all(r["class"] == "pit" and float(r["deviation_mm"]) > 1.5 for r in rows)
    everything = list(csv.DictReader(io.StringIO(client.get("/api/export.csv").text)))
    assert len(everything) == 5 and everything[4]["part_verdict"] == "ERROR"


def test_token_is_required_when_set(results):
    client = TestClient(create_app(results, token="s3cret-token"))
    assert client.get("/api/state").status_code == 401
    assert client.get("/").status_code == 401
    assert client.get("/", params={"token": "wrong-token!"}).status_code == 401
    page = client.get("/", params={"token": "s3cret-token"})
    assert page.status_code == 200 and "stereo-inspect" in page.text
    assert client.get("/api/state").status_code == 200  # the cookie set by the first visit
    bearer = TestClient(create_app(results, token="s3cret-token"))
    assert bearer.get("/api/state", headers={"Authorization": "Bearer s3cret-token"}).status_code == 200


def test_page_and_its_assets_are_served_locally(results):
    client = TestClient(create_app(results))
    page = client.get("/").text
    assert "/static/view.js" in page and "/static/view.css" in page
    assert "http://" not in page and "https://" not in page  # no CDN: the line has no internet
    for asset in ("/static/view.js", "/static/view.css"):
        response = client.get(asset)
        assert response.status_code == 200 and "https://" not in response.text


def test_live_frames_are_long_polled_newest_first(tmp_path, plane_sequence):
    outcomes = []
    folder, _ = _run(tmp_path, plane_sequence, save_images="none", on_part=outcomes.append)
    feed = LiveFeed()
    client = TestClient(create_app(folder, feed))
    assert client.get("/api/state").json()["run_id"] is None  # starting: the store's newest run is not this one
    assert client.get("/api/parts").json()["total"] == 0  # nor are its parts
    assert client.get("/api/export.csv").text.count("\n") == 1  # the header only
    assert client.get("/api/frame.jpg", params={"wait": 0}).status_code == 204
    feed.started("engine-test")
    feed.part(outcomes[0])
    first = client.get("/api/frame.jpg", params={"after": 0})
    assert first.status_code == 200 and first.headers["x-frame-seq"] == "1"
    assert cv2.imdecode(np.frombuffer(first.content, np.uint8), cv2.IMREAD_COLOR).shape[:2] == (192, 320)
    again = client.get("/api/frame.jpg", params={"after": 1, "wait": 0.1})  # nothing newer: the same frame
    assert again.headers["x-frame-seq"] == "1" and again.content == first.content and feed.encodes == 1
    feed.part(outcomes[1])
    second = client.get("/api/frame.jpg", params={"after": 1})
    assert second.headers["x-frame-seq"] == "2" and second.content != first.content
    state = client.get("/api/state").json()
    assert state["mode"] == "live" and state["verdict"] == {
        "status": "REJECT", "reasons": outcomes[1].part.verdict.reasons, "part_id": "R1-000001", "frame_id": "000001"}
    # save_images: none, yet the page can show the reject: the feed keeps recent rejects in memory
    image = client.get("/api/parts/R1-000001/image.jpg")
    assert image.status_code == 200 and image.headers["content-type"] == "image/jpeg"
    assert client.get("/api/parts/R1-000000/image.jpg").status_code == 404  # a pass is not kept
    assert client.get("/api/export.csv").status_code == 200


def test_the_line_does_no_view_work_while_nobody_watches(tmp_path, plane_sequence):
    feed = LiveFeed()
    _run(tmp_path, plane_sequence, on_part=feed.part)
    assert feed.seq == 5 and feed.encodes == 0


def test_live_counters_kept_by_the_feed_match_the_store(tmp_path, plane_sequence):
    feed = LiveFeed()
    folder, _ = _run(tmp_path, plane_sequence, on_part=feed.part)
    feed.started("engine-test")
    reader = StoreReader(folder)
    stored = reader.counters(1)
    assert (stored["parts"], stored["rejected"], stored["errors"], stored["rejects_per_class"]) == (5, 2, 1, {"pit": 2})
    assert counters(*feed.verdict_counts(), reader.alarm_count(1)) == stored
    assert TestClient(create_app(folder, feed)).get("/api/state").json()["counters"] == stored


def test_a_stalled_browser_does_not_hold_the_line(tmp_path, plane_sequence):
    """A browser that asks for frames and never reads them: the run still completes every part."""
    feed = LiveFeed()
    outcomes = []
    folder, _ = _run(tmp_path, plane_sequence, save_images="none", on_part=outcomes.append, break_frame=None)
    feed.part(outcomes[0])
    port = free_port()
    server = ViewServer(create_app(folder, feed), "127.0.0.1", port).start()
    stalled = socket.create_connection(("127.0.0.1", port))
    stalled.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    try:
        stalled.sendall(b"".join(b"GET /api/frame.jpg?wait=0 HTTP/1.1\r\nHost: x\r\n\r\n" for _ in range(200)))
        done = threading.Event()

        def line() -> None:
            for outcome in outcomes * 40:
                feed.part(outcome)
            done.set()

        worker = threading.Thread(target=line)
        worker.start()
        assert done.wait(60), "feeding parts blocked behind a browser that does not read"
        assert feed.seq == 1 + 5 * 40
        # and other browsers are still served
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/api/state", timeout=10) as response:
            assert response.status == 200
    finally:
        stalled.close()
        server.stop()


def test_exposure_warnings():
    assert is_loopback("127.0.0.1") and is_loopback("::1") and is_loopback("localhost")
    assert not is_loopback("0.0.0.0") and not is_loopback("192.168.1.20")
    assert exposure_warning("127.0.0.1", None) is None
    assert "WITHOUT AUTHENTICATION" in exposure_warning("0.0.0.0", None)
    assert "token" in exposure_warning("0.0.0.0", "s3cret-token")


def test_a_ctrl_c_that_comes_with_the_serving_message_ends_the_serving_not_the_command(tmp_path, plane_sequence):
    # the message printed before the wait began: a Ctrl-C straight after it ended `inspect run --keep-serving`
    # with "Aborted!" and exit 1 instead of the run's own exit code
    from core.commands.view import serve_until_interrupted

    folder, _ = _run(tmp_path, plane_sequence, save_images="none", break_frame=None)
    port = free_port()
    server = ViewServer(create_app(folder, LiveFeed()), "127.0.0.1", port).start()

    def interrupted_while_saying_so():
        raise KeyboardInterrupt

    serve_until_interrupted(server, interrupted_while_saying_so)
    with pytest.raises(OSError):
        socket.create_connection(("127.0.0.1", port), timeout=2).close()
