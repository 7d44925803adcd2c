"""The results store: SQLite in WAL mode, one row per part, per defect, per output event and alarm.

Each part is committed before its reject is handed to the outputs, so a crash loses nothing
that was decided; WAL lets a reviewer read the store while a run writes it.
"""
from __future__ import annotations

import csv
import functools
import io
import json
import math
import os
import socket
import sqlite3
import threading
import time
from collections import Counter
from pathlib import Path

from core import uncertainty_budget
from core.file_checks import unwritable
from core.types import Alarm, DefectMeasurement, OutputEvent, PartResult, Status, UncertaintyPart
from drivers.file_writes import write_text

DB_NAME = "results.db"
ROW_ID_MAX = 2**63 - 1  # SQLite's largest integer: a larger id overflows in the query, not "no such row"

SCHEMA = """
CREATE TABLE IF NOT EXISTS runs (
    id INTEGER PRIMARY KEY,
    recipe_name TEXT NOT NULL,
    recipe_hash TEXT NOT NULL,
    recipe_path TEXT NOT NULL,
    started REAL NOT NULL,
    finished REAL,
    parts INTEGER DEFAULT 0,
    passed INTEGER DEFAULT 0,
    rejected INTEGER DEFAULT 0,
    errors INTEGER DEFAULT 0,
    flagged INTEGER DEFAULT 0,
    alarms INTEGER DEFAULT 0,
    fps REAL,
    exit_code INTEGER
);
CREATE TABLE IF NOT EXISTS parts (
    id INTEGER PRIMARY KEY,
    run_id INTEGER NOT NULL REFERENCES runs(id),
    part_id TEXT NOT NULL,
    frame_id TEXT NOT NULL,
    frame_index INTEGER NOT NULL,
    time REAL NOT NULL,
    verdict TEXT NOT NULL,
    reasons TEXT NOT NULL,
    error TEXT,
    image_path TEXT
);
CREATE TABLE IF NOT EXISTS defects (
    id INTEGER PRIMARY KEY,
    part_row INTEGER NOT NULL REFERENCES parts(id),
    class TEXT NOT NULL,
    confidence REAL NOT NULL,
    x0 REAL, y0 REAL, x1 REAL, y1 REAL,
    distance_mm REAL,
    deviation_mm REAL,
    valid_fraction REAL,
    depth_resolution_mm REAL,
    area_mm2 REAL,
    verdict TEXT NOT NULL,
    reasons TEXT NOT NULL,
    note TEXT,
    distance_sigma_mm REAL,
    deviation_sigma_mm REAL,
    depth_method TEXT,
    uncertainty TEXT
);
CREATE TABLE IF NOT EXISTS output_events (
    id INTEGER PRIMARY KEY,
    run_id INTEGER NOT NULL REFERENCES runs(id),
    part_id TEXT,
    output TEXT NOT NULL,
    command TEXT NOT NULL,
    outcome TEXT NOT NULL,
    time REAL NOT NULL,
    detail TEXT
);
CREATE TABLE IF NOT EXISTS alarms (
    id INTEGER PRIMARY KEY,
    run_id INTEGER NOT NULL REFERENCES runs(id),
    source TEXT NOT NULL,
    message TEXT NOT NULL,
    time REAL NOT NULL,
    part_id TEXT,
    acknowledged INTEGER DEFAULT 0
);
CREATE INDEX IF NOT EXISTS parts_run ON parts(run_id);
CREATE INDEX IF NOT EXISTS parts_part_id ON parts(part_id);
CREATE INDEX IF NOT EXISTS defects_part ON defects(part_row);
"""
# Columns added after the first release, added to an older store when it is opened for writing.
ADDED_COLUMNS = (
    ("runs", "flagged", "INTEGER DEFAULT 0"),
    ("runs", "recipe_sha256", "TEXT"),  # the recipe file as run
    ("runs", "models", "TEXT"),  # JSON {weights file: SHA-256} of every model the run loaded
    ("runs", "status", "TEXT"),  # running, finished, crashed (found unfinished by a later run)
    ("runs", "pid", "INTEGER"),  # the process that wrote it, to tell a run still going from a crashed one
    ("runs", "outputs", "TEXT"),  # JSON list of the outputs a reject of this run goes to
    ("runs", "host", "TEXT"),
    ("defects", "distance_sigma_mm", "REAL"),
    ("defects", "deviation_sigma_mm", "REAL"),
    ("defects", "depth_method", "TEXT"),
    # JSON [{kind, cause, variance_mm2}]: what the deviation's uncertainty is made of (core/uncertainty_budget.py)
    ("defects", "uncertainty", "TEXT"),
)


def _columns(db: sqlite3.Connection, table: str) -> set[str]:
    return {row[1] for row in db.execute(f"PRAGMA table_info({table})")}


def _add_missing_columns(db: sqlite3.Connection) -> None:
    present = {table: _columns(db, table) for table in {t for t, _, _ in ADDED_COLUMNS}}
    for table, column, kind in ADDED_COLUMNS:
        if column not in present[table]:
            db.execute(f"ALTER TABLE {table} ADD COLUMN {column} {kind}")


class StoreError(Exception):
    """A results store that cannot be opened; ``str()`` is the one-line message naming the file."""


def _unusable(path: Path, exc: Exception) -> StoreError:
    return StoreError(f"{path}: not a results store that can be used ({exc}): move it aside or give another "
                      f"results.path")


def damaged(path: Path, exc: sqlite3.DatabaseError) -> StoreError:
    """A store whose tables open but whose pages do not read (a disk, or a copy, that went wrong)."""
    return StoreError(f"{path}: the results store is damaged ({exc}): move it aside (sqlite3's .recover can save "
                      f"what it holds) or give another results.path")


def _required_columns() -> dict[str, set[str]]:
    """Each table's columns that every version of the store has: the schema's less ``ADDED_COLUMNS``."""
    mem = sqlite3.connect(":memory:")
    mem.executescript(SCHEMA)
    tables = [row[0] for row in mem.execute("SELECT name FROM sqlite_master WHERE type = 'table'")]
    added = {(t, c) for t, c, _ in ADDED_COLUMNS}
    required = {t: {c for c in _columns(mem, t) if (t, c) not in added} for t in tables}
    mem.close()
    return required


REQUIRED_COLUMNS = _required_columns()


def schema_problem(db: sqlite3.Connection, tables: tuple[str, ...] = ()) -> str | None:
    """Why ``db`` is not a results store, or None: one of ``tables`` missing, or a table of the store's
    name without the columns every version of it has (another program's database)."""
    present = {row[0] for row in db.execute("SELECT name FROM sqlite_master WHERE type = 'table'")}
    missing_tables = [t for t in tables if t not in present]
    if missing_tables:
        return f"no table {', '.join(missing_tables)}"
    for table, columns in REQUIRED_COLUMNS.items():
        missing = columns - _columns(db, table) if table in present else set()
        if missing:
            return f"its table {table} has no column {', '.join(sorted(missing))}"
    return None


def store_problem(location: Path, tables: tuple[str, ...] = ()) -> str | None:
    """Why the store at ``location`` cannot be used (``schema_problem``, or not a database at all), or, where
    there is none yet, why it could not be made there (a file in its path, a folder not writable); in one
    line naming it, else None. Creates and changes nothing."""
    path = db_path(location)
    try:
        if not path.is_file():
            return _folder_problem(location, path)
    except OSError as exc:  # a folder that cannot be looked into
        return f"{location}: cannot be used ({exc.strerror or exc})"
    try:
        db = sqlite3.connect(path.resolve().as_uri() + "?mode=ro", uri=True)
        try:
            problem = schema_problem(db, tables)
        finally:
            db.close()
    except sqlite3.DatabaseError as exc:
        problem = str(exc)
    return None if problem is None else str(_unusable(path, problem))


def _folder_problem(location: Path, path: Path) -> str | None:
    """Why no store could be made at ``path`` (``location``'s database file, not there yet), or None."""
    problem = unwritable(path)
    if problem is None:
        return None
    return f"{location}: cannot be {'written' if problem.endswith('not writable') else 'created'} ({problem})"


def db_path(location: Path) -> Path:
    location = Path(location)
    return location if location.suffix == ".db" else location / DB_NAME


def _serialised(method):
    """One writer at a time on the store's connection: the run loop's thread, and the watch's thread when it
    records a stall while the loop is stuck elsewhere (a transaction must not take another's statements)."""
    @functools.wraps(method)
    def locked(self, *args, **kwargs):
        with self._lock:
            return method(self, *args, **kwargs)
    return locked


class ResultsStore:
    def __init__(self, location: Path):
        """``StoreError`` where the folder cannot be made or the file is not a store this version can use
        (another program's database, a damaged file): before a run starts, not at its first part."""
        self.path = db_path(location)
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise StoreError(f"{self.path.parent}: cannot create the results folder ({exc.strerror})") from None
        self._lock = threading.RLock()
        try:
            self.db = sqlite3.connect(self.path, check_same_thread=False)
        except sqlite3.Error as exc:
            raise StoreError(f"{self.path}: cannot open the results store ({exc})") from None
        try:
            problem = schema_problem(self.db)
            if problem is not None:
                raise sqlite3.DatabaseError(problem)
            self.db.execute("PRAGMA journal_mode=WAL")
            # FULL: a decided part survives a power cut, not only a crash of this process.
            self.db.execute("PRAGMA synchronous=FULL")
            self.db.executescript(SCHEMA)
            _add_missing_columns(self.db)
            self.db.commit()
        except sqlite3.DatabaseError as exc:
            self.db.close()
            raise _unusable(self.path, exc) from None

    @property
    def image_dir(self) -> Path:
        return self.path.parent / "images"

    @_serialised
    def start_run(self, recipe_name: str, recipe_hash: str, recipe_path: str, recipe_sha256: str | None = None,
                  models: dict[str, str] | None = None, outputs: list[str] | None = None) -> int:
        cur = self.db.execute(
            "INSERT INTO runs (recipe_name, recipe_hash, recipe_path, started, recipe_sha256, models, status, pid, host,"
            " outputs) VALUES (?, ?, ?, ?, ?, ?, 'running', ?, ?, ?)",
            (recipe_name, recipe_hash, recipe_path, time.time(), recipe_sha256, json.dumps(models or {}), os.getpid(),
             socket.gethostname(), json.dumps(outputs or [])),
        )
        self.db.commit()
        return int(cur.lastrowid)

    @_serialised
    def record_part(self, run_id: int, part: PartResult, defect_verdicts: list[tuple[Status, list[str]]]) -> int:
        with self.db:
            cur = self.db.execute(
                "INSERT INTO parts (run_id, part_id, frame_id, frame_index, time, verdict, reasons, error, image_path)"
                " VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?)",
                (run_id, part.part_id, part.frame_id, part.index, part.timestamp, part.verdict.status.value,
                 json.dumps(part.verdict.reasons), part.error, part.image_path),
            )
            row = int(cur.lastrowid)
            for m, (status, reasons) in zip(part.measurements, defect_verdicts):
                d = m.detection
                self.db.execute(
                    "INSERT INTO defects (part_row, class, confidence, x0, y0, x1, y1, distance_mm, deviation_mm,"
                    " valid_fraction, depth_resolution_mm, area_mm2, verdict, reasons, note, distance_sigma_mm,"
                    " deviation_sigma_mm, depth_method, uncertainty)"
                    " VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
                    (row, d.class_name, d.confidence, *d.box, m.distance_mm, m.deviation_mm, m.valid_fraction,
                     m.depth_resolution_mm, m.area_mm2, status.value, json.dumps(reasons), m.note,
                     m.distance_sigma_mm, m.deviation_sigma_mm, m.method, uncertainty_json(m)),
                )
        return row

    @_serialised
    def record_events(self, run_id: int, events: list[OutputEvent | Alarm]) -> None:
        if not events:
            return
        with self.db:
            for e in events:
                if isinstance(e, Alarm):
                    self.db.execute(
                        "INSERT INTO alarms (run_id, source, message, time, part_id) VALUES (?, ?, ?, ?, ?)",
                        (run_id, e.source, e.message, e.timestamp, e.part_id),
                    )
                else:
                    self.db.execute(
                        "INSERT INTO output_events (run_id, part_id, output, command, outcome, time, detail)"
                        " VALUES (?, ?, ?, ?, ?, ?, ?)",
                        (run_id, e.part_id, e.output, e.command, e.outcome, e.timestamp, e.detail),
                    )

    @_serialised
    def finish_run(self, run_id: int, counts: Counter, alarms: int, fps: float, exit_code: int) -> None:
        with self.db:
            self.db.execute(
                "UPDATE runs SET finished=?, parts=?, passed=?, rejected=?, errors=?, flagged=?, alarms=?, fps=?,"
                " exit_code=?, status='finished' WHERE id=?",
                (time.time(), sum(counts.values()), counts[Status.PASS], counts[Status.REJECT], counts[Status.ERROR],
                 counts[Status.FLAG], alarms, fps, exit_code, run_id),
            )

    def unfinished_runs(self) -> list[int]:
        """Runs that never finished and whose process is not running any more (on this host): a crash, a
        SIGKILL, a power cut. A run still being written by another process is left alone."""
        found = []
        for run_id, pid, host in self.db.execute(
                "SELECT id, pid, host FROM runs WHERE finished IS NULL AND (status IS NULL OR status = 'running')"):
            if host == socket.gethostname() and pid and _alive(pid):
                continue
            found.append(int(run_id))
        return found

    @_serialised
    def recover_crashed(self, run_ids: list[int], current_run: int) -> list[Alarm]:
        """Mark ``run_ids`` crashed, with counts from their parts, and return the alarms the operator must see:
        one per run, and one per REJECT, ERROR or FLAG part of it with no delivered output event (its reject
        may not have reached the actuator)."""
        alarms = []
        now = time.time()
        with self.db:
            for run_id in run_ids:
                verdicts = Counter(dict(self.db.execute(
                    "SELECT verdict, COUNT(*) FROM parts WHERE run_id = ? GROUP BY verdict", (run_id,)).fetchall()))
                self.db.execute(
                    "UPDATE runs SET status='crashed', parts=?, passed=?, rejected=?, errors=?, flagged=? WHERE id=?",
                    (sum(verdicts.values()), verdicts.get("PASS", 0), verdicts.get("REJECT", 0),
                     verdicts.get("ERROR", 0), verdicts.get("FLAG", 0), run_id))
                alarms.append(Alarm("store", f"run {run_id} ended without finishing (the process was killed or the "
                                    f"power cut) after {sum(verdicts.values())} parts; found by run {current_run}",
                                    now, None, "crash"))
                for part_id, verdict in unconfirmed_rejects(self.db, run_id):
                    alarms.append(Alarm("store", f"part {part_id} was {'rejected' if verdict == 'REJECT' else verdict} "
                                        f"but its reject may not have fired: run {run_id} stopped before its output "
                                        "confirmed it", now, part_id, "crash"))
        return alarms

    @_serialised
    def close(self) -> None:
        self.db.close()


def unconfirmed_rejects(db: sqlite3.Connection, run_id: int) -> list[tuple[str, str]]:
    """(part id, verdict) of the run's REJECT, ERROR and FLAG parts that some output of the run did not
    confirm as delivered: each output a reject goes to (the PLC, a log) must have said so."""
    row = db.execute("SELECT outputs FROM runs WHERE id = ?", (run_id,)).fetchone()
    outputs = json.loads(row[0]) if row and row[0] else []
    delivered: dict[str, set[str]] = {}
    for part_id, output in db.execute("SELECT DISTINCT part_id, output FROM output_events WHERE run_id = ? AND "
                                      "outcome = 'delivered' AND part_id IS NOT NULL", (run_id,)):
        delivered.setdefault(part_id, set()).add(output)
    needed = set(outputs) or {"*"}
    return [(part_id, verdict) for part_id, verdict in db.execute(
        "SELECT part_id, verdict FROM parts WHERE run_id = ? AND verdict != 'PASS' ORDER BY id", (run_id,))
        if not (needed <= delivered.get(part_id, set()) or (needed == {"*"} and part_id in delivered))]


def _alive(pid: int) -> bool:
    if pid == os.getpid():
        return False  # a run of this process left unfinished (a test, an earlier run in the same process)
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def open_readonly(location: Path) -> sqlite3.Connection:
    path = db_path(location)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no results store here")
    # every table the first release made: report and view read them all
    problem = store_problem(path, tables=tuple(REQUIRED_COLUMNS))
    if problem is not None:
        raise StoreError(problem)
    db = sqlite3.connect(path.resolve().as_uri() + "?mode=ro", uri=True)
    db.row_factory = sqlite3.Row
    return db


def summary(db: sqlite3.Connection, run_id: int | None = None) -> dict:
    args = () if run_id is None else (run_id,)
    where = "" if run_id is None else "WHERE run_id = ?"
    where_parts = "" if run_id is None else "WHERE p.run_id = ?"
    verdicts = Counter(dict(db.execute(f"SELECT verdict, COUNT(*) FROM parts {where} GROUP BY verdict", args).fetchall()))
    per_class: dict[str, Counter] = {}
    for cls, verdict, n in db.execute(
        f"SELECT d.class, d.verdict, COUNT(*) FROM defects d JOIN parts p ON p.id = d.part_row {where_parts}"
        " GROUP BY d.class, d.verdict", args
    ).fetchall():
        per_class.setdefault(cls, Counter())[verdict] += n
    alarms = db.execute(f"SELECT COUNT(*) FROM alarms {where}", args).fetchone()[0]
    return {**verdict_counts(verdicts), "defects_per_class": {c: dict(v) for c, v in sorted(per_class.items())},
            "alarms": alarms}


def undecided_by_cause(db: sqlite3.Connection, run_id: int | None = None) -> dict[str, int]:
    """The defects a ``deviation_mm`` rule could not decide, by the largest part of their deviation's uncertainty
    (its kind, ``core.uncertainty_budget.KINDS``; "" for a defect without an account, such as the backend's map
    alone), most first; empty for a store from before the account was kept."""
    from core.decision import NOT_PROVEN

    if "uncertainty" not in _columns(db, "defects"):
        return {}
    where, args = ("AND p.run_id = ?", (run_id,)) if run_id is not None else ("", ())
    tally: Counter = Counter()
    for reasons, text in db.execute(
            "SELECT d.reasons, d.uncertainty FROM defects d JOIN parts p ON p.id = d.part_row WHERE d.reasons LIKE ?"
            f" {where}", (f"%{NOT_PROVEN}%", *args)):
        # the account is the deviation's: a defect that only a rule on another quantity left undecided is not its
        if not any(NOT_PROVEN in r and "deviation_mm" in r for r in _reasons(reasons)):
            continue
        tally[uncertainty_budget.largest_kind([UncertaintyPart(p["kind"], p["cause"], p["variance_mm2"])
                                               for p in uncertainty_account(text)])] += 1
    return dict(tally.most_common())


def _reasons(text: str) -> list[str]:
    try:
        reasons = json.loads(text)
    except ValueError:
        return []
    return [r for r in reasons if isinstance(r, str)] if isinstance(reasons, list) else []


def uncertainty_account(text: str | None) -> list[dict]:
    """A defect's ``uncertainty`` column as a list of {kind, cause, variance_mm2}; empty where there is none, or
    where what the column holds is not such a list (a store another program wrote to): no account to show."""
    try:
        parts = json.loads(text) if text else []
    except ValueError:
        return []
    ok = isinstance(parts, list) and all(isinstance(p, dict) and isinstance(p.get("kind"), str)
                                         and isinstance(p.get("cause"), str)
                                         and isinstance(p.get("variance_mm2"), (int, float))
                                         and math.isfinite(p["variance_mm2"]) for p in parts)
    return parts if ok else []


def uncertainty_json(m: DefectMeasurement) -> str | None:
    """A measurement's ``uncertainty_parts`` as the store keeps them, None without an account or with a part that is
    not a number (a JSON reader, the page's among them, would refuse the NaN)."""
    if not m.uncertainty_parts or not all(math.isfinite(p.variance_mm2) for p in m.uncertainty_parts):
        return None
    return json.dumps([{"kind": p.kind, "cause": p.cause, "variance_mm2": p.variance_mm2} for p in m.uncertainty_parts])


def verdict_counts(verdicts: dict[str, int]) -> dict:
    """Parts, passed, rejected, errors, flagged and the yield in % (None without parts) from parts per verdict:
    what `inspect report` and the operator page count alike."""
    parts = sum(verdicts.values())
    return {
        "parts": parts,
        "passed": verdicts.get("PASS", 0),
        "rejected": verdicts.get("REJECT", 0),
        "errors": verdicts.get("ERROR", 0),
        "flagged": verdicts.get("FLAG", 0),
        "yield_percent": round(100.0 * verdicts.get("PASS", 0) / parts, 1) if parts else None,
    }


def crashed_runs(db: sqlite3.Connection, run_id: int | None = None) -> list[dict]:
    """Runs a later run found unfinished, with their parts and the rejects no output confirmed."""
    if "status" not in _columns(db, "runs"):
        return []
    where, args = ("AND r.id = ?", (run_id,)) if run_id is not None else ("", ())
    rows = db.execute(
        "SELECT r.id, (SELECT COUNT(*) FROM parts p WHERE p.run_id = r.id) AS parts"
        f" FROM runs r WHERE r.status = 'crashed' {where} ORDER BY r.id", args).fetchall()
    return [{"id": r[0], "parts": r[1], "unconfirmed": len(unconfirmed_rejects(db, r[0]))} for r in rows]


def master_part_checks(db: sqlite3.Connection, run_id: int | None = None) -> list[tuple[int, bool, str]]:
    """Each run's master-part check (``core.verification``), by run: (run id, whether the line started on it,
    its tally or the alarm that kept the line from starting)."""
    where, args = ("AND run_id = ?", (run_id,)) if run_id is not None else ("", ())
    rows = db.execute(
        f"SELECT run_id, 1, detail, id FROM output_events WHERE output = 'verify' {where}"
        f" UNION ALL SELECT run_id, 0, message, id FROM alarms WHERE source = 'verify' {where}"
        " ORDER BY 1, 4", args + args).fetchall()
    return [(r[0], bool(r[1]), r[2] or "") for r in rows]


CSV_COLUMNS = [
    "run_id", "part_id", "frame_id", "time", "part_verdict", "part_reasons", "error", "class", "confidence",
    "x0", "y0", "x1", "y1", "distance_mm", "deviation_mm", "valid_fraction", "depth_resolution_mm", "area_mm2",
    "defect_verdict", "defect_reasons", "distance_sigma_mm", "deviation_sigma_mm", "depth_method", "uncertainty",
]


def csv_rows(db: sqlite3.Connection, run_id: int | None = None, verdict: str | None = None,
             defect_class: str | None = None) -> list[tuple]:
    """One row per defect (a part without defects gets one row with empty defect columns), in
    ``CSV_COLUMNS`` order; the filters keep the parts of one run, of one verdict, or with a defect of one class."""
    where, args = part_filter(run_id, verdict, defect_class)
    rows = db.execute(
        "SELECT p.run_id, p.part_id, p.frame_id, p.time, p.verdict, p.reasons, p.error, d.class, d.confidence,"
        " d.x0, d.y0, d.x1, d.y1, d.distance_mm, d.deviation_mm, d.valid_fraction, d.depth_resolution_mm,"
        f" d.area_mm2, d.verdict, d.reasons, {_added(db, 'defects', 'd')}"
        f" FROM parts p LEFT JOIN defects d ON d.part_row = p.id {where} ORDER BY p.id, d.id",
        args,
    ).fetchall()
    return [tuple(r) for r in rows]


def _added(db: sqlite3.Connection, table: str, alias: str) -> str:
    """The columns ADDED_COLUMNS gives ``table``, as a select list: NULL for each that a store made by an
    older version (opened read-only, so not migrated) lacks."""
    present = _columns(db, table)
    return ", ".join(f"{alias}.{c}" if c in present else "NULL" for t, c, _ in ADDED_COLUMNS if t == table)


def part_filter(run_id: int | None, verdict: str | None, defect_class: str | None) -> tuple[str, list]:
    clauses, args = [], []
    if run_id is not None:
        clauses.append("p.run_id = ?")
        args.append(run_id)
    if verdict is not None:
        clauses.append("p.verdict = ?")
        args.append(verdict)
    if defect_class is not None:
        clauses.append("EXISTS (SELECT 1 FROM defects dc WHERE dc.part_row = p.id AND dc.class = ?)")
        args.append(defect_class)
    return ("WHERE " + " AND ".join(clauses)) if clauses else "", args


def write_csv(rows: list[tuple], out) -> None:
    writer = csv.writer(out)
    writer.writerow(CSV_COLUMNS)
    writer.writerows(rows)


def export_csv(db: sqlite3.Connection, out: Path, run_id: int | None = None) -> int:
    """Every part (of one run, or of all), one row per defect."""
    rows = csv_rows(db, run_id)
    text = io.StringIO(newline="")
    write_csv(rows, text)
    write_text(out, text.getvalue())
    return len(rows)
