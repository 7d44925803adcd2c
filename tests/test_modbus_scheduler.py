"""``drivers.reject_scheduler`` on its own, with a small in-process link (a list with a clock)."""
from __future__ import annotations

import time

from drivers.reject_scheduler import Command, LinkError, RejectScheduler


class ListLink:
    """Keeps what it was sent with the time; ``fail`` makes the next sends raise."""

    def __init__(self):
        self.sent: list[tuple[float, object]] = []
        self.fail: list[Exception] = []
        self.connects = 0

    def connect(self) -> None:
        self.connects += 1

    def close(self) -> None:
        pass

    def send(self, command) -> str:
        if self.fail:
            raise self.fail.pop(0)
        self.sent.append((time.time(), command))
        return ""


def test_commands_fire_in_due_order_not_submit_order():
    link = ListLink()
    sched = RejectScheduler(link, "t")
    now = time.time()
    sched.submit("b", Command("B", "B"), now + 0.2)
    sched.submit("a", Command("A", "A"), now + 0.1)
    records = sched.close(timeout_s=2)
    assert [c for _, c in link.sent] == ["A", "B"]
    assert [(r.key, r.outcome) for r in records] == [("a", "delivered"), ("b", "delivered")]


def test_an_unexpected_exception_is_retried_and_the_worker_survives():
    link = ListLink()
    link.fail = [RuntimeError("library bug"), LinkError("timeout")]
    sched = RejectScheduler(link, "t", max_late_s=0.3, reconnect_min_s=0.01)
    sched.submit("p", Command("X", "X"), time.time() + 0.05)
    records = sched.close(timeout_s=2)
    mine = [r for r in records if r.key == "p"]
    assert [r.outcome for r in mine] == ["failed", "failed", "delivered"]
    assert "library bug" in mine[0].detail and "timeout" in mine[1].detail
    assert [c for _, c in link.sent] == ["X"]
    assert link.connects >= 3


def test_heartbeat_never_turns_into_an_alarm_at_close():
    link = ListLink()
    sched = RejectScheduler(link, "t", heartbeat=lambda n: Command(("beat", n), f"beat {n}"), heartbeat_period_s=0.02)
    time.sleep(0.15)
    started = time.monotonic()
    records = sched.close(timeout_s=2)
    assert time.monotonic() - started < 0.5
    assert not [r for r in records if r.alarm]
    assert len([c for _, c in link.sent if c[0] == "beat"]) >= 3


def test_a_heartbeat_too_far_apart_to_wait_for_leaves_the_worker_alive():
    # waiting for a beat 1e300 s off raised OverflowError in the worker, which died: every reject after it
    # stayed queued, unsent and unalarmed, until the output was closed
    link = ListLink()
    sched = RejectScheduler(link, "t", heartbeat=lambda n: Command(("beat", n), f"beat {n}"), heartbeat_period_s=1e300)
    time.sleep(0.1)  # the first beat is sent, the next one is due in 1e300 s
    sched.submit("p", Command("X", "X"), time.time() + 0.05)
    time.sleep(0.5)
    assert [c for _, c in link.sent][-1] == "X"  # sent when due, not at close
    records = sched.close(timeout_s=2)
    assert [r.outcome for r in records if r.key == "p"] == ["delivered"]


def test_a_worker_that_stops_on_an_error_of_its_own_alarms_every_reject_at_once():
    # the worker died (as the overflow of a heartbeat 1e300 ms off made it): every reject after it stayed
    # queued, unsent and unalarmed, until the output was closed
    def beat(n):
        if n == 1:
            raise ValueError("register address out of range")
        return Command(("beat", n), f"beat {n}")

    link = ListLink()
    sched = RejectScheduler(link, "t", heartbeat=beat, heartbeat_period_s=0.01, where="the PLC")
    time.sleep(0.2)
    sched.submit("p", Command("X", "X"), time.time() + 0.05)
    records = sched.drain()
    said = [r.alarm for r in records if r.alarm]
    assert said == ["the PLC: the output's sender stopped (ValueError: register address out of range): rejects "
                    "cannot reach the actuator",
                    "X for p not sent: the output's sender stopped (ValueError: register address out of range)"]
    assert [c for _, c in link.sent if c == "X"] == []
    assert not [r for r in sched.close(timeout_s=1) if r.key == "p"]  # alarmed once, when submitted
