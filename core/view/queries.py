"""What the operator view reads from a results store. Each call opens its own connection: the
engine writes the store from another thread, and SQLite's WAL lets both go on at once."""
from __future__ import annotations

import json
import sqlite3
from contextlib import contextmanager
from pathlib import Path

from core import store

FILMSTRIP_LENGTH = 12


class StoreReader:
    def __init__(self, location: Path):
        self.path = store.db_path(location)

    @contextmanager
    def _db(self, write: bool = False):
        if not self.path.is_file():
            yield None
            return
        # as_uri() percent-encodes, so a folder name with '?' or '#' stays a path
        uri = self.path.resolve().as_uri() + ("" if write else "?mode=ro")
        db = sqlite3.connect(uri, uri=True, timeout=5.0)
        db.row_factory = sqlite3.Row
        try:
            yield db
        finally:
            db.close()

    def runs(self) -> list[dict]:
        with self._db() as db:
            if db is None:
                return []
            # counted, not the runs.parts column: that is written when a run finishes, and a run
            # in progress has parts too
            return [dict(r) for r in db.execute(
                "SELECT id, recipe_name, started, finished, (SELECT COUNT(*) FROM parts p WHERE p.run_id = runs.id)"
                " AS parts, exit_code FROM runs ORDER BY id DESC")]

    def latest_run(self) -> int | None:
        with self._db() as db:
            if db is None:
                return None
            row = db.execute("SELECT MAX(id) FROM runs").fetchone()
            return row[0]

    def counters(self, run_id: int | None) -> dict:
        with self._db() as db:
            if db is None or run_id is None:
                return counters({}, {}, 0)
            s = store.summary(db, run_id)
        rejects = {cls: by.get("REJECT", 0) for cls, by in s["defects_per_class"].items()}
        return counters({"PASS": s["passed"], "REJECT": s["rejected"], "ERROR": s["errors"], "FLAG": s["flagged"]},
                        rejects, s["alarms"])

    def alarm_count(self, run_id: int | None) -> int:
        with self._db() as db:
            if db is None or run_id is None:
                return 0
            return db.execute("SELECT COUNT(*) FROM alarms WHERE run_id = ?", (run_id,)).fetchone()[0]

    def filmstrip(self, run_id: int | None, length: int = FILMSTRIP_LENGTH) -> list[dict]:
        """The run's last parts that did not pass (REJECT, FLAG and ERROR), newest first."""
        with self._db() as db:
            if db is None or run_id is None:
                return []
            rows = db.execute(
                "SELECT p.id, p.part_id, p.frame_id, p.time, p.verdict, p.reasons,"
                " (SELECT GROUP_CONCAT(DISTINCT d.class) FROM defects d WHERE d.part_row = p.id AND d.verdict != 'PASS') AS classes"
                " FROM parts p WHERE p.run_id = ? AND p.verdict != 'PASS' ORDER BY p.id DESC LIMIT ?",
                (run_id, length),
            ).fetchall()
        return [_part_summary(r) for r in rows]

    def parts(self, run_id: int | None, verdict: str | None, defect_class: str | None, page: int, per_page: int) -> dict:
        """One page of a run's parts; no run (a live run not yet started, an empty store) has none."""
        with self._db() as db:
            if db is None or run_id is None:
                return {"total": 0, "page": page, "per_page": per_page, "parts": []}
            where, args = store.part_filter(run_id, verdict, defect_class)
            total = db.execute(f"SELECT COUNT(*) FROM parts p {where}", args).fetchone()[0]
            rows = db.execute(
                "SELECT p.id, p.part_id, p.frame_id, p.time, p.verdict, p.reasons,"
                " (SELECT GROUP_CONCAT(DISTINCT d.class) FROM defects d WHERE d.part_row = p.id) AS classes"
                f" FROM parts p {where} ORDER BY p.id DESC LIMIT ? OFFSET ?",
                # a page beyond every row SQLite can hold is as empty as the next one, not an overflow
                (*args, per_page, min((page - 1) * per_page, store.ROW_ID_MAX)),
            ).fetchall()
        return {"total": total, "page": page, "per_page": per_page, "parts": [_part_summary(r) for r in rows]}

    def classes(self) -> list[str]:
        with self._db() as db:
            if db is None:
                return []
            return [r[0] for r in db.execute("SELECT DISTINCT class FROM defects ORDER BY class")]

    def part(self, part_id: str) -> dict | None:
        with self._db() as db:
            if db is None:
                return None
            row = db.execute("SELECT * FROM parts WHERE part_id = ? ORDER BY id DESC LIMIT 1", (part_id,)).fetchone()
            if row is None:
                return None
            defects = db.execute("SELECT * FROM defects WHERE part_row = ? ORDER BY id", (row["id"],)).fetchall()
            events = db.execute(
                "SELECT output, command, outcome, time, detail FROM output_events WHERE part_id = ? AND run_id = ? ORDER BY id",
                (part_id, row["run_id"]),
            ).fetchall()
        part = dict(row)
        part["reasons"] = json.loads(part["reasons"])
        # a store from before the account of the uncertainty was kept has no such column: an empty account
        part["defects"] = [{**dict(d), "reasons": json.loads(d["reasons"]),
                            "uncertainty": store.uncertainty_account(d["uncertainty"] if "uncertainty" in d.keys()
                                                                     else None)} for d in defects]
        part["output_events"] = [dict(e) for e in events]
        return part

    def master_parts(self, run_id: int | None) -> dict | None:
        """The run's master-part check (``store.master_part_checks``): {"started": whether the line started on
        it, "text": its tally or the alarm}; None where the run had none."""
        with self._db() as db:
            if db is None or run_id is None:
                return None
            checks = store.master_part_checks(db, run_id)
        if not checks:
            return None
        _, started, text = checks[-1]
        return {"started": started, "text": text}

    def alarms(self, run_id: int | None) -> list[dict]:
        """The run's alarms not yet acknowledged, newest first."""
        with self._db() as db:
            if db is None or run_id is None:
                return []
            return [dict(r) for r in db.execute(
                "SELECT id, source, message, time, part_id, acknowledged FROM alarms WHERE run_id = ? AND acknowledged = 0"
                " ORDER BY id DESC LIMIT 100",
                (run_id,),
            )]

    def acknowledge(self, alarm_id: int) -> bool:
        with self._db(write=True) as db:
            if db is None:
                return False
            with db:
                cur = db.execute("UPDATE alarms SET acknowledged = 1 WHERE id = ?", (alarm_id,))
            return cur.rowcount == 1

    def csv_rows(self, run_id: int | None, verdict: str | None, defect_class: str | None) -> list[tuple]:
        with self._db() as db:
            if db is None or run_id is None:
                return []
            return store.csv_rows(db, run_id, verdict, defect_class)


def counters(verdicts: dict[str, int], rejects_per_class: dict[str, int], alarms: int) -> dict:
    """The page's counters from parts per verdict and rejected defects per class."""
    return {**store.verdict_counts(verdicts),
            "rejects_per_class": {cls: n for cls, n in sorted(rejects_per_class.items()) if n}, "alarms": alarms}


def _part_summary(row: sqlite3.Row) -> dict:
    return {
        "part_id": row["part_id"],
        "frame_id": row["frame_id"],
        "time": row["time"],
        "verdict": row["verdict"],
        "reasons": json.loads(row["reasons"]),
        "classes": sorted(set(row["classes"].split(","))) if row["classes"] else [],
    }
