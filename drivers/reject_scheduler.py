"""Fire commands at their due time, in order, over a link that may come and go.

The actuator sits downstream of the camera: a reject decided now must be fired when the part
reaches it. ``RejectScheduler`` keeps a queue ordered by due time and one worker thread that

* waits (no busy loop) until the earliest command is due and sends it over the ``Link``;
* reconnects with exponential back-off while the link is down, also between commands, so the
  link is up again before the next one is due; a connection that drops after a command went through is
  reopened at once, one that opens but takes no command (a peer refusing it) only after the back-off,
  so that a refused command is not retried thousands of times a second against the PLC;
* gives each command until ``due + max_late_s`` (its deadline); a command that cannot be sent
  by then is reported with outcome ``alarm`` and never silently dropped;
* runs follow-up commands (a coil pulse's release) and an optional periodic heartbeat;
* tells the line the inspection is not ready while it is held (``hold``: the ``on_close`` command, no
  heartbeat; the inspection behind it has stalled) and ready again on ``release``;
* keeps pulses apart: a command with a follow-up (a pulse) is not started while the previous
  pulse is still on, plus ``min_pulse_gap_s``, because the actuator would see one long pulse for
  two parts. If waiting for the gap would miss the deadline, the command is an alarm;
* knows the actuator's state: on every (re)connect the ``idle`` commands (each coil and register the
  output owns, back at rest) are sent before anything else, and a pulse whose release could not be
  sent is an alarm naming its part, after which the idle state is re-established before the next
  command, so that a rising edge is only ever written to a coil known to be low;
* reports a link that cannot be reached as an alarm, with or without commands waiting.

Every outcome is a ``Record``; ``drain()`` hands over what happened since the last call.
This module imports nothing from the rest of stereo-inspect: any object with ``connect()``,
``close()`` and ``send(command)`` is a link (see ``modbus_link`` and ``serial_line``).
"""
from __future__ import annotations

import heapq
import itertools
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Protocol


class LinkError(Exception):
    """The link could not connect or a command was not acknowledged; the message says why."""


class LinkRefused(LinkError):
    """The peer answered and refused the command (an address, a value or a function it does not have): a
    setting to correct, not a cable to check."""


class Link(Protocol):
    def connect(self) -> None:
        """Open the connection; raise ``LinkError`` (or ``OSError``) when it cannot."""

    def close(self) -> None: ...

    def send(self, command: Any) -> str:
        """Send one command and wait for its acknowledgement; return a short detail.
        Raise ``LinkError``/``OSError`` when it fails (the scheduler reconnects and retries)."""


MIN_PULSE_GAP_S = 0.02  # a coil low at least this long between two pulses, so that the PLC sees two rising edges
# the longest the worker sleeps at once: a wait for a time too far off (a heartbeat every 1e300 ms) raised
# OverflowError in the worker, which died, and every later reject stayed queued, unsent and unalarmed, until close
MAX_WAIT_S = 1.0


@dataclass
class Command:
    """What to send for a part. ``follow_up`` is sent ``follow_up_after_s`` after it succeeds."""

    payload: Any
    text: str
    follow_up: Command | None = None
    follow_up_after_s: float = 0.0


@dataclass
class Record:
    """One outcome: ``delivered``, ``failed`` (an attempt failed; it is retried) or ``alarm``."""

    key: str | None
    text: str
    outcome: str
    timestamp: float
    detail: str = ""
    alarm: str | None = None  # set when the operator must hear about it
    late_s: float | None = None  # sent this long after the due time (delivered records)
    # why an alarm was raised: link (unreachable), refused (the peer refused a command), late (handed over after
    # its due time), busy, pulse (would merge with the previous), release (a pulse's end not sent), closed
    cause: str | None = None


@dataclass(order=True)
class _Job:
    due: float  # time.monotonic()
    seq: int
    deadline: float = field(compare=False)
    key: str | None = field(compare=False)
    command: Command = field(compare=False)
    kind: str = field(compare=False, default="part")  # part | follow-up | heartbeat | state
    attempts: int = field(compare=False, default=0)
    submitted: float = field(compare=False, default_factory=time.monotonic)


SERVICE = ("heartbeat", "state")  # jobs that keep the line informed, not commands for a part


class RejectScheduler:
    def __init__(
        self,
        link: Link,
        name: str = "output",
        *,
        max_late_s: float = 0.1,
        reconnect_min_s: float = 0.05,
        reconnect_max_s: float = 2.0,
        on_connect: Command | None = None,
        on_close: Command | None = None,
        idle: list[Command] | None = None,
        where: str = "the link",
        heartbeat: Callable[[int], Command] | None = None,
        heartbeat_period_s: float = 1.0,
        record_failures: bool = True,
        min_pulse_gap_s: float = MIN_PULSE_GAP_S,
    ):
        self.link, self.name = link, name
        self.max_late_s = max_late_s
        self.reconnect_min_s, self.reconnect_max_s = reconnect_min_s, reconnect_max_s
        self.on_connect, self.on_close = on_connect, on_close
        self.idle = list(idle or [])
        self.where = where
        self._idle_known = False  # the idle commands went through since the last connect or failed release
        self.heartbeat, self.heartbeat_period_s = heartbeat, heartbeat_period_s
        self.record_failures = record_failures
        self.min_pulse_gap_s = min_pulse_gap_s
        self._pulse_until = 0.0  # monotonic time the last pulse's release is due
        self._cond = threading.Condition()
        self._queue: list[_Job] = []
        self._records: list[Record] = []
        self._seq = itertools.count()
        self._connected = False
        self._answered = False  # a command went through on this connection
        self._backoff = reconnect_min_s
        self._next_connect = 0.0
        self._last_connect_error = ""
        self._refused = False  # the last error was the peer refusing a command, not the link failing
        self._down_reported = False
        self._closing = False
        self._stop = False
        self._inflight: _Job | None = None
        self._beat = 0
        self._held = False
        self._failed: str | None = None  # the worker stopped on an error of its own: why
        self._thread = threading.Thread(target=self._run, name=f"{name} scheduler", daemon=True)
        if heartbeat is not None:
            self._push(time.monotonic(), None, heartbeat(0), "heartbeat", deadline=float("inf"))
        self._thread.start()

    # ------------------------------------------------------------------ public
    def submit(self, key: str | None, command: Command, due_wall: float) -> None:
        """Queue ``command`` for ``due_wall`` (a ``time.time()`` value). Never blocks for long."""
        due = time.monotonic() + (due_wall - time.time())
        with self._cond:
            if self._closing or self._failed:
                why = f"the output's sender stopped ({self._failed})" if self._failed else "output already closed"
                self._records.append(Record(key, command.text, "alarm", time.time(), why,
                                            alarm=f"{command.text} for {key} not sent: {why}", cause="closed"))
                return
            self._push_locked(due, key, command, "part", due + self.max_late_s)
            self._cond.notify_all()

    def hold(self) -> None:
        """The inspection behind this output has stalled: send ``on_close`` (the line is told it is not
        ready) and no heartbeat until ``release``. Commands for parts still go out when due."""
        with self._cond:
            if self._held or self._closing:
                return
            self._held = True
            if self.on_close is not None:
                self._push_locked(time.monotonic(), None, self.on_close, "state", float("inf"))
            self._cond.notify_all()

    def release(self) -> None:
        """The inspection is running again: send ``on_connect`` and beat again."""
        with self._cond:
            if not self._held or self._closing:
                return
            self._held = False
            if self.on_connect is not None:
                self._push_locked(time.monotonic(), None, self.on_connect, "state", float("inf"))
            self._cond.notify_all()

    def drain(self) -> list[Record]:
        with self._cond:
            records, self._records = self._records, []
        return records

    @property
    def pending(self) -> int:
        with self._cond:
            return sum(1 for j in self._queue if j.kind not in SERVICE)

    @property
    def connected(self) -> bool:
        return self._connected

    def last_due_in(self) -> float:
        """Seconds until the last queued command is due (0 when none is waiting)."""
        with self._cond:
            dues = [j.due for j in self._queue if j.kind not in SERVICE]
        return max(0.0, max(dues) - time.monotonic()) if dues else 0.0

    def close(self, timeout_s: float = 10.0, why: str | None = None) -> list[Record]:
        """Send everything queued (waiting for commands not yet due, up to ``timeout_s``), alarm
        what cannot be sent (saying ``why`` where given), release the link, and return the remaining records.
        May be called again after a close that was interrupted."""
        end = time.monotonic() + timeout_s
        with self._cond:
            self._closing = True
            self._queue = [j for j in self._queue if j.kind not in SERVICE]
            heapq.heapify(self._queue)
            self._cond.notify_all()
            while self._busy_locked() and time.monotonic() < end and self._thread.is_alive():
                self._cond.wait(min(0.05, max(0.0, end - time.monotonic())))
            leftover = [j for j in self._queue if j.kind not in SERVICE]
            self._queue = []
            self._stop = True
            self._cond.notify_all()
            now = time.time()
            for job in sorted(leftover):
                self._alarm_locked(job, now, why or f"not sent: output closed after {timeout_s:g} s with it still "
                                   f"queued", "closed")
        self._thread.join(max(1.0, end - time.monotonic() + 1.0))
        if self._connected and self.on_close is not None:
            try:
                self.link.send(self.on_close.payload)
                self._records.append(Record(None, self.on_close.text, "delivered", time.time()))
            except Exception as exc:
                self._records.append(Record(None, self.on_close.text, "failed", time.time(), str(exc)))
        try:
            self.link.close()
        except Exception:
            pass
        self._connected = False
        return self.drain()

    # ----------------------------------------------------------------- worker
    def _busy_locked(self) -> bool:
        if self._inflight is not None and self._inflight.kind not in SERVICE:
            return True
        return any(j.kind not in SERVICE for j in self._queue)

    def _push(self, due: float, key, command: Command, kind: str, deadline: float) -> None:
        with self._cond:
            self._push_locked(due, key, command, kind, deadline)

    def _push_locked(self, due: float, key, command: Command, kind: str, deadline: float) -> None:
        heapq.heappush(self._queue, _Job(due, next(self._seq), deadline, key, command, kind))

    def _alarm_locked(self, job: _Job, now: float, why: str, cause: str | None = None) -> None:
        if job.kind == "follow-up":  # the actuator may still be on: say so, for the part it was for
            message = (f"part {job.key}: the end of its pulse ({job.command.text}) was not sent, {why}; the output "
                       "may have stayed on until the PLC is reached again, when it is set back to rest")
            self._idle_known = False
            cause = "release"
        else:
            message = f"{job.command.text} for {job.key} {why}" if job.key else f"{job.command.text} {why}"
        self._records.append(Record(job.key, job.command.text, "alarm", now, why, alarm=message, cause=cause))

    def _run(self) -> None:
        try:
            self._work()
        except Exception as exc:  # an error of the worker's own: every reject queued or to come would wait, unsent
            self._stopped_by(exc)

    def _stopped_by(self, exc: Exception) -> None:
        """The worker cannot go on: say so once, and alarm every command queued now (and, in ``submit``, every one
        to come) instead of letting them wait, unsent, for the output's close."""
        with self._cond:
            self._failed = f"{type(exc).__name__}: {exc}"
            now = time.time()
            self._records.append(Record(None, "worker", "alarm", now, self._failed, cause="closed",
                                        alarm=f"{self.where}: the output's sender stopped ({self._failed}): rejects "
                                              f"cannot reach the actuator"))
            queued = [j for j in self._queue if j.kind not in SERVICE]
            if self._inflight is not None and self._inflight.kind not in SERVICE:
                queued.append(self._inflight)
            self._queue, self._inflight = [], None
            for job in sorted(queued):
                self._alarm_locked(job, now, f"not sent: the output's sender stopped ({self._failed})", "closed")
            self._cond.notify_all()

    def _work(self) -> None:
        while True:
            with self._cond:
                if self._stop:
                    return
                now = time.monotonic()
                job = self._queue[0] if self._queue else None
                wake = job.due if job is not None else now + 0.5
                if not self._connected:
                    wake = min(wake, max(self._next_connect, now))
                if wake > now:
                    self._cond.wait(min(wake - now, MAX_WAIT_S))
                    continue
                if job is not None and job.due <= now:
                    self._inflight = heapq.heappop(self._queue)
                else:
                    job = None
            if not self._connected and time.monotonic() >= self._next_connect:
                self._try_connect()
            if job is None:
                continue
            try:
                self._attempt(job)
            finally:
                with self._cond:
                    self._inflight = None
                    self._cond.notify_all()

    def _try_connect(self) -> None:
        try:
            self.link.connect()
            # the connection counts as up once the outputs are at rest (a socket that opens and then drops
            # every request is as unreachable as a refused one)
            for command in self.idle:
                try:
                    detail = self.link.send(command.payload)
                except Exception:
                    try:
                        self.link.close()
                    except Exception:
                        pass
                    raise
                self._went_through()
                with self._cond:
                    self._records.append(Record(None, command.text, "delivered", time.time(), detail or ""))
        except Exception as exc:  # LinkError, OSError, or anything a library raises: keep the worker alive
            self._last_connect_error = str(exc) or exc.__class__.__name__
            self._refused = isinstance(exc, LinkRefused)
            self._next_connect = time.monotonic() + self._backoff
            self._backoff = min(self.reconnect_max_s, self._backoff * 2)
            if not self._down_reported:
                self._down_reported = True
                if self._refused:
                    cause, alarm = "refused", (f"{self.where} refuses the output's commands ({self._last_connect_error}): "
                                               "rejects cannot reach the actuator until the recipe or the PLC is set right")
                else:
                    cause, alarm = "link", (f"{self.where} cannot be reached ({self._last_connect_error}): rejects cannot "
                                            "reach the actuator until it answers")
                with self._cond:
                    self._records.append(Record(None, "connect", "alarm", time.time(), self._last_connect_error,
                                                cause=cause, alarm=alarm))
            return
        self._connected = True
        if self._down_reported:
            with self._cond:
                self._records.append(Record(None, "connect", "delivered", time.time(), "link up again"))
        self._down_reported = False
        self._idle_known = True
        # held: the line hears "not ready" again (the PLC may have kept the last value while the link was down)
        state = self.on_close if self._held else self.on_connect
        if state is not None:
            try:
                detail = self.link.send(state.payload)
                self._went_through()
                with self._cond:
                    self._records.append(Record(None, state.text, "delivered", time.time(), detail or ""))
            except Exception as exc:
                self._lost(exc)

    def _went_through(self) -> None:
        self._answered = True
        self._backoff = self.reconnect_min_s

    def _lost(self, exc: Exception) -> None:
        self._connected = False
        self._last_connect_error = str(exc) or exc.__class__.__name__
        self._refused = isinstance(exc, LinkRefused)
        try:
            self.link.close()
        except Exception:
            pass
        if self._answered:  # it worked until now: a dropped connection is worth reopening at once
            self._next_connect = time.monotonic()
        else:  # it opens but takes nothing: reopening at once would retry the command in a tight loop
            self._next_connect = time.monotonic() + self._backoff
            self._backoff = min(self.reconnect_max_s, self._backoff * 2)
        self._answered = False

    def _attempt(self, job: _Job) -> None:
        if job.kind == "heartbeat":
            self._heartbeat(job)
            return
        if job.kind == "state":
            self._state(job)
            return
        if job.command.follow_up is not None and not self._pulse_apart(job):
            return
        while True:
            now = time.monotonic()
            if now > job.deadline:
                if job.submitted > job.deadline:
                    cause = (f"handed over {(job.submitted - job.due) * 1000:.0f} ms after its due time "
                             "(inspection took longer than the delay to the actuator)")
                    kind = "late"
                elif self._connected:
                    cause, kind = "earlier commands kept the link busy", "busy"
                else:
                    cause, kind = self._last_connect_error or "link down", "refused" if self._refused else "link"
                why = f"not sent by its deadline ({self.max_late_s * 1000:.0f} ms after due): {cause}"
                with self._cond:
                    self._alarm_locked(job, time.time(), why, kind)
                return
            if self._connected and not self._idle_known:  # a release failed: back to rest before anything else
                self._lost(LinkError("re-establishing the outputs' rest state"))
            if not self._connected:
                if now < self._next_connect:
                    with self._cond:
                        if self._stop:
                            self._alarm_locked(job, time.time(), "not sent: output closed while the link was down")
                            return
                        self._cond.wait(min(self._next_connect, job.deadline + 1e-3) - now)
                    continue
                self._try_connect()
                if not self._connected:
                    continue
            job.attempts += 1
            started = time.monotonic()
            try:
                detail = self.link.send(job.command.payload)
            except Exception as exc:  # LinkError, OSError, or a library's own: retried until the deadline
                if self.record_failures:
                    with self._cond:
                        self._records.append(Record(job.key, job.command.text, "failed", time.time(),
                                                    f"attempt {job.attempts}: {exc}"))
                self._lost(exc)
                continue
            self._went_through()
            done = time.monotonic()
            late = started - job.due  # when the command went out; the answer may take a little longer
            with self._cond:
                if started > job.deadline:
                    why = f"sent {late * 1000:.0f} ms after its due time (limit {self.max_late_s * 1000:.0f} ms)"
                    self._alarm_locked(job, time.time(), why, "late" if job.submitted > job.deadline else "link")
                else:
                    self._records.append(Record(job.key, job.command.text, "delivered", time.time(),
                                                f"sent {late * 1000:+.0f} ms vs due, confirmed after {(done - started) * 1000:.0f} ms"
                                                + (f"; {detail}" if detail else ""), late_s=late))
                if job.command.follow_up is not None:
                    follow = job.command.follow_up
                    due = done + job.command.follow_up_after_s
                    self._pulse_until = due
                    # a release must still happen even if late; alarm only when it is badly late
                    self._push_locked(due, job.key, follow, "follow-up", due + max(1.0, 10 * self.max_late_s))
                    self._cond.notify_all()
            return

    def _pulse_apart(self, job: _Job) -> bool:
        """True when ``job`` (a pulse) may start now; otherwise it is re-queued after the previous
        pulse's release (which the queue runs first), or alarmed when that is past its deadline."""
        ready = self._pulse_until + self.min_pulse_gap_s
        if time.monotonic() >= ready:
            return True
        with self._cond:
            if ready > job.deadline:
                self._alarm_locked(job, time.time(), "not sent: it would merge with the previous part's pulse "
                                   f"(pulses need {self.min_pulse_gap_s * 1000:.0f} ms between them; parts come closer "
                                   "together than the pulse length: shorten the pulse or use a counter register)",
                                   "pulse")
            else:
                heapq.heappush(self._queue, _Job(ready, next(self._seq), job.deadline, job.key, job.command, job.kind,
                                                 job.attempts, job.submitted))
                self._cond.notify_all()
        return False

    def _state(self, job: _Job) -> None:
        """Ready or not ready (``hold``/``release``): sent now if connected, else on the next connect."""
        if not self._connected or self._closing:
            return
        try:
            detail = self.link.send(job.command.payload)
        except Exception as exc:
            with self._cond:
                self._records.append(Record(None, job.command.text, "failed", time.time(), str(exc)))
            self._lost(exc)
            return
        self._went_through()
        with self._cond:
            self._records.append(Record(None, job.command.text, "delivered", time.time(), detail or ""))

    def _heartbeat(self, job: _Job) -> None:
        if self._connected and not self._closing and not self._held:
            try:
                self.link.send(job.command.payload)
                self._went_through()
            except Exception as exc:
                self._lost(exc)
        with self._cond:
            if not self._closing and self.heartbeat is not None:
                self._beat += 1
                self._push_locked(time.monotonic() + self.heartbeat_period_s, None, self.heartbeat(self._beat),
                                  "heartbeat", float("inf"))
