"""Fault injection: the real line under damaged frames, a cut PLC link and a killed process, then an account
of every part (``inspect sim faults``).

The demo sequence is copied with some frames cut short (truncated JPEGs) and replayed in a loop by a real
``inspect run`` process. Its Modbus output reaches the PLC simulator (a real pymodbus server) through a
TCP proxy that is cut and restored at random times. The process is killed with SIGKILL at random times
and started again, and finally stopped with SIGTERM. Afterwards, over every run in the results store:

- each REJECT, ERROR or FLAG part was delivered to the PLC or is named by an alarm (of its own run, or of
  the crash recovery of the run after it);
- each delivered reject is one rising edge of the reject coil at the PLC, near the time it was reported;
- no part of a damaged frame passed;
- the store passes ``PRAGMA integrity_check``.
"""
from __future__ import annotations

import json
import random
import shutil
import signal
import sqlite3
import subprocess
import sys
import threading
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

from drivers import plc_sim
from drivers.file_writes import write_text
from sim.tcp_proxy import TcpProxy

ROOT = Path(__file__).resolve().parents[1]
RECIPE = ROOT / "recipes" / "steel_plate.yaml"
SEQUENCE = ROOT / "sim_fixtures" / "steel_plate"
EDGE_MATCH_S = 1.0  # a delivered reject and its rising edge at the PLC, at most this far apart


class FaultsError(Exception):
    """The line could not be run under faults at all (``inspect run`` stopped by itself); the message says why."""


@dataclass
class FaultReport:
    parts: int = 0
    runs: int = 0
    passed: int = 0
    rejected: int = 0
    errors: int = 0
    flagged: int = 0
    damaged_frames: list[str] = field(default_factory=list)
    damaged_parts: int = 0
    cuts: int = 0
    kills: int = 0
    delivered: int = 0
    alarmed: int = 0
    crash_alarms: int = 0
    rising_edges: int = 0
    unaccounted: list[str] = field(default_factory=list)  # rejects neither delivered nor alarmed
    passed_damaged: list[str] = field(default_factory=list)
    delivered_without_edge: list[str] = field(default_factory=list)
    integrity: str = ""

    @property
    def ok(self) -> bool:
        return (not self.unaccounted and not self.passed_damaged and not self.delivered_without_edge
                and self.integrity == "ok" and self.parts > 0)

    def lines(self) -> list[str]:
        return [
            f"parts {self.parts} over {self.runs} runs: passed {self.passed}, rejected {self.rejected}, "
            f"errors {self.errors}, flagged {self.flagged}",
            f"faults: {len(self.damaged_frames)} damaged frames ({self.damaged_parts} parts of them), "
            f"{self.cuts} link cuts, {self.kills} kills",
            f"rejects: {self.delivered} delivered (PLC rising edges {self.rising_edges}), {self.alarmed} alarmed "
            f"({self.crash_alarms} by crash recovery)",
            f"unaccounted rejects: {len(self.unaccounted)}; passes from damaged frames: {len(self.passed_damaged)}; "
            f"delivered without a rising edge: {len(self.delivered_without_edge)}; integrity_check: {self.integrity}",
        ]


def damaged_copy(out: Path, copies: int, share: float, rng: random.Random) -> list[str]:
    """The demo sequence ``copies`` times over in ``out`` (frame ids 000000...), with ``share`` of the frames'
    left or right JPEG cut to 30-70 % of its bytes; returns the damaged frame ids."""
    if out.exists():
        shutil.rmtree(out)
    (out / "left").mkdir(parents=True)
    (out / "right").mkdir()
    (out / "labels").mkdir()
    shutil.copy(SEQUENCE / "calib.yaml", out / "calib.yaml")
    sources = sorted(p.stem for p in (SEQUENCE / "left").glob("*.jpg"))
    damaged = []
    n = 0
    for _ in range(copies):
        for stem in sources:
            frame_id = f"{n:06d}"
            for eye in ("left", "right"):
                shutil.copy(SEQUENCE / eye / f"{stem}.jpg", out / eye / f"{frame_id}.jpg")
            shutil.copy(SEQUENCE / "labels" / f"{stem}.json", out / "labels" / f"{frame_id}.json")
            if rng.random() < share:
                victim = out / rng.choice(("left", "right")) / f"{frame_id}.jpg"
                data = victim.read_bytes()
                victim.write_bytes(data[: int(rng.uniform(0.3, 0.7) * len(data))])
                damaged.append(frame_id)
            n += 1
    return damaged


def _cutter(proxy: TcpProxy, stop: threading.Event, rng: random.Random, every: tuple[float, float],
            lasting: tuple[float, float]) -> None:
    while not stop.wait(rng.uniform(*every)):
        proxy.cut()
        if stop.wait(rng.uniform(*lasting)):
            break
        proxy.restore()
    proxy.restore()


def _parts(results: Path) -> int:
    try:
        with sqlite3.connect(results / "results.db", timeout=2) as db:
            return db.execute("SELECT COUNT(*) FROM parts").fetchone()[0]
    except sqlite3.Error:
        return 0


def run_faults(out: Path, parts: int = 200, kills: int = 2, seed: int = 0, damage: float = 0.1,
               overrides: tuple[str, ...] = (), rate_fps: float = 6.0, log=print) -> FaultReport:
    """The whole run (module docstring); returns the account. ``overrides`` go to ``inspect run --set``."""
    rng = random.Random(seed)
    out = Path(out).resolve()  # inspect run resolves relative paths against the recipe's folder
    out.mkdir(parents=True, exist_ok=True)
    results = out / "results"
    if results.exists():
        shutil.rmtree(results)
    (out / "inspect_run.log").unlink(missing_ok=True)  # each run's alarms as it printed them
    report = FaultReport(damaged_frames=damaged_copy(out / "seq", 4, damage, rng))
    port = plc_sim.free_port()
    exe = Path(sys.executable).parent / "inspect"
    args = [str(exe), "run", str(RECIPE), "--quiet", "--set", f"camera.settings.path={out / 'seq'}",
            "--set", "camera.settings.loop=true", "--set", f"camera.settings.rate_fps={rate_fps}",
            "--set", f"results.path={results}", "--set", f"outputs.1.settings.file={out / 'rejects.log'}",
            "--set", "outputs.0.settings.reconnect_max_ms=300"]
    for item in overrides:
        args += ["--set", item]
    kill_at = sorted(rng.uniform(0.2, 0.8) * parts for _ in range(kills))
    stop = threading.Event()
    with plc_sim.serve_in_thread("127.0.0.1", port, on_change=None) as sim, TcpProxy(port) as proxy:
        args += ["--set", f"outputs.0.settings.port={proxy.port}"]
        cutter = threading.Thread(target=_cutter, args=(proxy, stop, rng, (2.0, 6.0), (0.3, 2.0)), daemon=True)
        cutter.start()
        try:
            while True:
                # its alarms to a file: a pipe nobody reads while the run goes on fills, and then blocks the run
                with open(out / "inspect_run.log", "ab") as said_to:
                    start = said_to.tell()
                    proc = subprocess.Popen(args, stdout=subprocess.DEVNULL, stderr=said_to)
                report.runs += 1
                target = kill_at.pop(0) if kill_at else parts
                while _parts(results) < target and proc.poll() is None:
                    time.sleep(0.2)
                if proc.poll() is not None:
                    with open(out / "inspect_run.log", "rb") as said_to:
                        said_to.seek(start)
                        said = [line for line in said_to.read().decode(errors="replace").splitlines() if line.strip()]
                    raise FaultsError(f"inspect run ended by itself (exit {proc.returncode})"
                                      + (f": {said[-1]}" if said else ""))
                if target < parts:
                    proc.kill()
                    proc.wait(30)
                    report.kills += 1
                    log(f"killed after {_parts(results)} parts")
                    continue
                proc.send_signal(signal.SIGTERM)
                proc.wait(180)
                break
        finally:
            stop.set()
            cutter.join(5)
        report.cuts = proxy.cuts
        # every killed run was found and recovered by the run started after it; the last one ends by SIGTERM
        edges = [w.timestamp for i, w in enumerate(sim.writes) if w.table == "coil" and w.address == 0 and w.value == 1
                 and _was_low(sim.writes, i)]
    account(results, report, edges)
    write_text(out / "faults.json", json.dumps({**asdict(report), "ok": report.ok}, indent=1))
    return report


def _was_low(writes, index: int) -> bool:
    """The coil was at 0 (or never written) before write ``index``: a rising edge, not a repeated 1."""
    for w in reversed(writes[:index]):
        if w.table == "coil" and w.address == writes[index].address and w.unit == writes[index].unit:
            return w.value == 0
    return True


def account(results: Path, report: FaultReport, edges: list[float]) -> FaultReport:
    """Fill ``report`` from the results store and the PLC's rising edges (module docstring)."""
    db = sqlite3.connect(results / "results.db")
    report.integrity = db.execute("PRAGMA integrity_check").fetchone()[0]
    rows = db.execute("SELECT part_id, frame_id, verdict FROM parts").fetchall()
    report.parts = len(rows)
    counts = {v: 0 for v in ("PASS", "REJECT", "ERROR", "FLAG")}
    for _, _, verdict in rows:
        counts[verdict] = counts.get(verdict, 0) + 1
    report.passed, report.rejected, report.errors, report.flagged = (counts["PASS"], counts["REJECT"], counts["ERROR"],
                                                                     counts["FLAG"])
    damaged = set(report.damaged_frames)
    report.damaged_parts = sum(1 for _, frame, _ in rows if frame in damaged)
    report.passed_damaged = [p for p, frame, verdict in rows if frame in damaged and verdict == "PASS"]
    delivered = {p: t for p, t in db.execute(
        "SELECT part_id, MIN(time) FROM output_events WHERE output = 'modbus' AND outcome = 'delivered' AND "
        "command LIKE '%(pulse%' GROUP BY part_id")}
    alarmed = {r[0] for r in db.execute("SELECT DISTINCT part_id FROM alarms WHERE part_id IS NOT NULL")}
    crash = {r[0] for r in db.execute("SELECT DISTINCT part_id FROM alarms WHERE part_id IS NOT NULL AND source = 'store'")}
    rejects = [p for p, _, verdict in rows if verdict != "PASS"]
    report.delivered = sum(1 for p in rejects if p in delivered)
    report.alarmed = sum(1 for p in rejects if p in alarmed)
    report.crash_alarms = sum(1 for p in rejects if p in crash)
    report.unaccounted = [p for p in rejects if p not in delivered and p not in alarmed]
    report.rising_edges = len(edges)
    free = sorted(edges)
    for part_id, t in sorted(delivered.items(), key=lambda kv: kv[1]):
        # the event is written when the PLC confirmed the write: its edge came just before
        match = next((e for e in free if abs(e - t) <= EDGE_MATCH_S), None)
        if match is None:
            report.delivered_without_edge.append(part_id)
        else:
            free.remove(match)
    db.close()
    return report
