"""The ``modbus`` reject output against a real pymodbus server (the PLC simulator) on 127.0.0.1.

Timing tolerance: a write must reach the PLC within TOL_S = 100 ms of its due time (part
timestamp + delay). On this 2-core machine, loaded, the measured lateness is a few ms.
"""
from __future__ import annotations

import re
import time

import pytest

from core.types import Alarm, OutputEvent, PartResult, Status, Verdict
from drivers import plc_sim
from plugins.modbus_output import ModbusOutput, ModbusSettings

TOL_S = 0.100
TRANSIT_S = 0.050  # send -> PLC receipt on loopback, for writes sent at the edge of their deadline
HOST = "127.0.0.1"


def part(i: int, status: Status = Status.REJECT, t: float | None = None) -> PartResult:
    return PartResult(f"P{i:04d}", f"{i:06d}", i, time.time() if t is None else t, Verdict(status))


def output(port: int, **settings) -> ModbusOutput:
    base = {"host": HOST, "port": port, "delay_ms": 300, "timeout_ms": 150, "reconnect_min_ms": 50,
            "reconnect_max_ms": 200, "on_reject": {"write": "coil", "address": 0, "pulse_ms": 60}}
    base.update(settings)
    return ModbusOutput(ModbusSettings.model_validate(base))


def events_of(events, kind=OutputEvent):
    return [e for e in events if isinstance(e, kind)]


@pytest.fixture
def port() -> int:
    return plc_sim.free_port()


@pytest.fixture
def sim(port):
    lines: list[str] = []
    s = plc_sim.serve_in_thread(HOST, port, on_change=lines.append)
    s.lines = lines
    yield s
    s.stop()


def coil_on_times(sim, address: int = 0) -> list[float]:
    return [w.timestamp for w in sim.writes if w.table == "coil" and w.address == address and w.value == 1]


def test_every_reject_arrives_as_a_coil_pulse_at_its_delay_in_order(sim, port):
    out = output(port, on_pass={"write": "register", "address": 10, "value": 7})
    statuses = [Status.REJECT, Status.PASS, Status.REJECT, Status.ERROR, Status.PASS, Status.REJECT]
    parts = []
    for i, status in enumerate(statuses):
        parts.append(part(i, status))
        out.submit(parts[-1])
        time.sleep(0.1)
    events = out.poll() + out.close(timeout_s=3)
    rejects = [p for p in parts if p.verdict.status.rejects]
    on = coil_on_times(sim)
    assert len(on) == len(rejects)
    for t, p in zip(on, rejects):
        assert abs(t - (p.timestamp + 0.3)) < TOL_S, f"{p.part_id}: {t - p.timestamp - 0.3:+.3f} s"
    coil = [w for w in sim.writes if w.table == "coil" and w.address == 0]
    assert coil[0].value == 0  # on connecting, the reject coil is put at rest before any pulse
    offs = [w for w in coil[1:] if w.value == 0]
    assert len(offs) == len(rejects)
    for t_on, off in zip(on, offs):
        assert 0.06 - 0.02 < off.timestamp - t_on < 0.06 + TOL_S
    passes = [w for w in sim.writes if w.table == "register" and w.address == 10]
    assert [w.value for w in passes] == [7, 7]
    delivered = [e for e in events_of(events) if e.outcome == "delivered" and "(pulse " in e.command]
    assert [e.part_id for e in delivered] == [p.part_id for p in rejects]
    assert delivered[0].command == "write_coil 0 = 1 unit 1 (pulse 60 ms)"
    assert not events_of(events, Alarm)
    assert sim.coil(0) == 0
    assert any(line.endswith("coil 0 -> 1") for line in sim.lines)


def test_delay_from_actuator_distance_and_belt_speed(sim, port):
    out = output(port, delay_ms=None, actuator_distance_mm=100, conveyor_speed_mm_s=400,
                 on_reject={"write": "register", "address": 3, "value": 42})
    p = part(1)
    out.submit(p)
    events = out.close(timeout_s=2)
    writes = [w for w in sim.writes if w.table == "register" and w.address == 3]
    assert [w.value for w in writes] == [42]
    assert abs(writes[0].timestamp - (p.timestamp + 0.25)) < TOL_S
    assert [e.outcome for e in events_of(events)] == ["delivered"]
    assert events_of(events)[0].command == "write_register 3 = 42 unit 1"


def test_counter_register_sees_every_reject_even_when_close_together(sim, port):
    out = output(port, delay_ms=100, on_reject={"write": "counter", "address": 20})
    for i in range(4):
        out.submit(part(i))
    events = out.close(timeout_s=2)
    assert [w.value for w in sim.writes if w.address == 20] == [1, 2, 3, 4]
    assert [e.command for e in events_of(events)][0] == "write_register 20 = 1 unit 1 (part counter)"


def test_close_rejects_give_separate_pulses(sim, port):
    """Two plates 30 ms apart, 60 ms pulses: the second pulse waits for the first to end, so the
    actuator sees two rising edges, each within the lateness limit."""
    out = output(port, max_late_ms=200)
    t = time.time()
    out.submit(part(1, t=t))
    out.submit(part(2, t=t + 0.03))
    events = out.close(timeout_s=3)
    on = coil_on_times(sim)
    offs = [w.timestamp for w in sim.writes if w.table == "coil" and w.address == 0 and w.value == 0][1:]  # after rest
    assert len(on) == 2 and len(offs) == 2
    assert offs[0] < on[1]  # released before the next pulse
    assert on[1] - (t + 0.33) < 0.2 + 0.05
    assert not events_of(events, Alarm)


def test_rejects_too_close_for_a_pulse_are_alarmed_not_merged(sim, port):
    # the second pulse could start 50 ms late at the earliest (the first one's 60 ms, less 10 ms): 40 ms
    # refuses it, and leaves the first one the room a loaded machine needs (20 ms once made the first late)
    out = output(port, max_late_ms=40)
    t = time.time()
    out.submit(part(1, t=t))
    out.submit(part(2, t=t + 0.01))
    events = out.close(timeout_s=3)
    assert len(coil_on_times(sim)) == 1
    alarms = events_of(events, Alarm)
    assert len(alarms) == 1 and alarms[0].part_id == "P0002" and "merge with the previous part's pulse" in alarms[0].message


def test_unit_id_ready_coil_and_heartbeat(sim, port):
    out = output(port, unit=3, ready_coil=5, heartbeat={"address": 100, "period_ms": 100})
    time.sleep(0.45)
    assert sim.coil(5, unit=3) == 1
    assert sim.register(100, unit=3) >= 2
    out.submit(part(1))
    events = out.close(timeout_s=2)
    assert sim.coil(5, unit=3) == 0
    commands = [e.command for e in events_of(events)]
    assert "write_coil 5 = 0 unit 3 (system stopped)" in commands
    assert "write_coil 0 = 1 unit 3 (pulse 60 ms)" in commands


def test_plc_down_at_start_then_up_before_due(port):
    out = output(port, delay_ms=600)
    p = part(1)
    out.submit(p)
    time.sleep(0.25)
    assert not out.scheduler.connected
    sim = plc_sim.serve_in_thread(HOST, port, on_change=None)
    try:
        events = out.close(timeout_s=3)
    finally:
        sim.stop()
    on = coil_on_times(sim)
    assert len(on) == 1 and abs(on[0] - (p.timestamp + 0.6)) < TOL_S
    outcomes = [(e.command, e.outcome) for e in events_of(events)]
    assert ("connect", "alarm") in outcomes and ("connect", "delivered") in outcomes
    # the PLC not answering is an alarm of its own, even though the reject then went out in time
    (alarm,) = events_of(events, Alarm)
    assert alarm.part_id is None and alarm.cause == "link" and "cannot be reached" in alarm.message


def test_plc_never_there_every_reject_is_an_alarm(port):
    out = output(port, delay_ms=100, max_late_ms=100)
    parts = [part(i) for i in range(3)]
    for p in parts:
        out.submit(p)
    started = time.monotonic()
    events = out.poll() + out.close(timeout_s=2)
    assert time.monotonic() - started < 1.5
    alarms = [a for a in events_of(events, Alarm) if a.part_id]
    assert [a.part_id for a in alarms] == [p.part_id for p in parts]
    assert all("cannot connect to the PLC at 127.0.0.1" in a.message for a in alarms)
    assert [a.cause for a in events_of(events, Alarm) if a.part_id is None] == ["link"]
    alarm_events = [e for e in events_of(events) if e.outcome == "alarm" and e.part_id]
    assert [e.part_id for e in alarm_events] == [p.part_id for p in parts]


def test_an_address_the_plc_does_not_have_is_a_refusal_that_says_so_not_an_unreachable_plc(sim, port):
    """The PLC answers with Modbus exception 2 (illegal data address): a setting to correct, not a cable."""
    out = output(port, delay_ms=100, max_late_ms=100, on_reject={"write": "coil", "address": plc_sim.SIZE,
                                                                 "pulse_ms": 60})
    parts = [part(i) for i in range(2)]
    for p in parts:
        out.submit(p)
    events = out.poll() + out.close(timeout_s=2)
    alarms = events_of(events, Alarm)
    assert {a.cause for a in alarms} == {"refused"}
    (link,) = [a for a in alarms if a.part_id is None]
    assert link.message.startswith(f"the PLC at {HOST}:{port} refuses the output's commands ({HOST}:{port}: the PLC "
                                   f"refused write_coil {plc_sim.SIZE} = 0 unit 1: it has no such address (illegal "
                                   f"data address) (Modbus exception 2) - check the recipe's address")
    assert [a.part_id for a in alarms if a.part_id] == [p.part_id for p in parts]
    assert coil_on_times(sim, plc_sim.SIZE) == []
    from conftest import ROOT

    from core.commands.inspection import alarm_hints
    from core.recipe import load_recipe

    hints = alarm_hints(alarms, load_recipe(ROOT / "recipes" / "steel_plate.yaml"), plc_sim_given=True)
    assert any("refused a command" in h and "addresses, unit and values" in h for h in hints)
    assert not any("did not answer" in h for h in hints)


def test_a_refused_command_is_retried_with_back_off_not_in_a_tight_loop(sim, port):
    """A register the PLC does not have: the connection opens, the write is refused. Reopened at once after
    each refusal, it was written about 2,000 times in its second of retries, a connection each."""
    out = output(port, delay_ms=100, max_late_ms=1000, reconnect_min_ms=50, reconnect_max_ms=400,
                 on_reject={"write": "register", "address": plc_sim.SIZE, "value": 1})
    out.submit(part(0))
    time.sleep(1.3)
    events = out.poll() + out.close(timeout_s=2)
    failed = [e for e in events_of(events) if e.outcome == "failed"]
    assert 3 <= len(failed) <= 10, len(failed)  # after 0, 50, 100, 200 and 400 ms of back-off, then every 400
    assert [(a.part_id, a.cause) for a in events_of(events, Alarm)] == [("P0000", "refused")]


def test_plc_killed_mid_run_and_restarted(port):
    """Parts every 80 ms for 1.6 s; the PLC is stopped after 0.5 s and back at 0.9 s. Every reject
    is delivered (on time) or alarmed, in order, and the output reconnects by itself."""
    sims = [plc_sim.serve_in_thread(HOST, port, on_change=None)]
    out = output(port, delay_ms=150, max_late_ms=100)
    parts = []
    start = time.monotonic()
    restarted = killed = False
    while time.monotonic() - start < 1.6:
        parts.append(part(len(parts)))
        out.submit(parts[-1])
        elapsed = time.monotonic() - start
        if elapsed > 0.5 and not killed:
            sims[0].stop()
            killed = True
        if elapsed > 0.9 and not restarted:
            sims.append(plc_sim.serve_in_thread(HOST, port, on_change=None))
            restarted = True
        time.sleep(0.08)
    events = out.close(timeout_s=3)
    for s in sims:
        s.stop()
    by_part: dict[str, str] = {}
    for e in events_of(events):
        if e.part_id and "(pulse " in e.command and e.outcome in ("delivered", "alarm"):
            by_part[e.part_id] = e.outcome
    assert set(by_part) == {p.part_id for p in parts}, "a reject vanished"
    alarmed = {a.part_id for a in events_of(events, Alarm) if a.part_id}
    assert alarmed == {k for k, v in by_part.items() if v == "alarm"}
    assert any(a.cause == "link" for a in events_of(events, Alarm)), "the outage itself is an alarm"
    assert alarmed, "the outage should have cost some rejects"
    delivered = [p for p in parts if by_part[p.part_id] == "delivered"]
    assert len(delivered) >= len(parts) // 2
    on = sorted(coil_on_times(sims[0]) + coil_on_times(sims[1]))
    assert len(on) >= len(delivered)
    assert by_part[parts[-1].part_id] == "delivered", "the output did not reconnect"
    ons_after = coil_on_times(sims[1])
    late_parts = [p for p in delivered if p.timestamp + 0.15 >= ons_after[0] - TOL_S]
    for p, t in zip(late_parts, ons_after):
        # a reject waiting for the reconnect may go out up to max_late_ms after its due time (the
        # output's contract); the PLC sees it that late plus the write's transit on loopback
        assert -TOL_S < t - (p.timestamp + 0.15) < 0.100 + TRANSIT_S, f"{p.part_id}: {t - p.timestamp - 0.15:+.3f} s"


def test_slow_plc_alarms_then_recovers(sim, port):
    sim.set_delay(0.4)
    out = output(port, delay_ms=50, timeout_ms=150, max_late_ms=100, reconnect_max_ms=50)
    slow = part(1)
    out.submit(slow)
    time.sleep(0.6)
    sim.set_delay(0.0)
    fast = part(2)
    out.submit(fast)
    events = out.poll() + out.close(timeout_s=2)
    alarms = events_of(events, Alarm)
    # a PLC slower than the timeout cannot be reached in time: said once, and the slow part's reject
    assert [(a.part_id, a.cause) for a in alarms] == [(None, "link"), (slow.part_id, "link")]
    assert "No response" in alarms[0].message  # the reason, from the PLC's silence
    ok = [e for e in events_of(events) if e.part_id == fast.part_id and "(pulse " in e.command]
    assert [e.outcome for e in ok] == ["delivered"]


def test_part_handed_over_after_its_deadline_is_an_alarm_that_says_why(sim, port):
    out = output(port, delay_ms=100, max_late_ms=50)
    out.submit(part(1, t=time.time() - 0.5))  # inspection took 500 ms, the actuator was 100 ms away
    events = out.close(timeout_s=1)
    alarms = events_of(events, Alarm)
    assert len(alarms) == 1 and "inspection took longer than the delay to the actuator" in alarms[0].message
    assert not coil_on_times(sim)


def test_close_waits_for_rejects_not_yet_due(sim, port):
    out = output(port, delay_ms=400)
    p = part(1)
    out.submit(p)
    events = out.close(timeout_s=2)
    assert [e.outcome for e in events_of(events) if "(pulse " in e.command] == ["delivered"]
    out2 = output(port, delay_ms=800)
    p2 = part(2)
    out2.submit(p2)
    events = out2.close(timeout_s=0.1)  # shorter than the delay: the plate on its way still gets its reject
    assert [e.outcome for e in events_of(events) if "(pulse " in e.command] == ["delivered"]
    assert abs(coil_on_times(sim)[-1] - (p2.timestamp + 0.8)) < TOL_S
    out3 = output(port, delay_ms=2000)
    out3.submit(part(3))
    events = out3.scheduler.close(timeout_s=0.2)  # the scheduler itself honours its timeout
    assert [r.key for r in events if r.alarm] == ["P0003"]
    assert "output closed" in [r.alarm for r in events if r.alarm][0]


def test_settings_are_checked():
    from pydantic import ValidationError

    with pytest.raises(ValidationError, match="either delay_ms or actuator_distance_mm"):
        ModbusSettings.model_validate({"delay_ms": 10, "actuator_distance_mm": 100, "conveyor_speed_mm_s": 10})
    with pytest.raises(ValidationError, match="go together"):
        ModbusSettings.model_validate({"actuator_distance_mm": 100})
    # the belt's speed in m/s: each reject would have fired 25 minutes later, at another plate
    with pytest.raises(ValidationError, match=r"the actuator would be 1500 s after the camera \(600 mm at 0.4 mm/s\): "
                                              "longer than the 120 s a run's end waits"):
        ModbusSettings.model_validate({"actuator_distance_mm": 600, "conveyor_speed_mm_s": 0.4})
    with pytest.raises(ValidationError, match=r"200 s after the camera \(delay_ms 200000\)"):
        ModbusSettings.model_validate({"delay_ms": 200000})
    with pytest.raises(ValidationError, match="rtu needs serial_port"):
        ModbusSettings.model_validate({"transport": "rtu", "delay_ms": 500})
    # each reached the first connection as "the PLC at ... cannot be reached", an alarm per reject
    for host, says in (("", "empty: give the PLC's IP address or host name"),
                       ("plc:502", "give the port as `port`, not in the host"),
                       ("tcp://10.0.0.5", "is a URL"), ("10.0.0.256", "'10.0.0.256' is not an IPv4 address"),
                       ("plc lan", "'plc lan' is not a host name")):
        with pytest.raises(ValidationError, match=re.escape(says)):
            ModbusSettings.model_validate({"host": host, "delay_ms": 500})
    for host in ("10.0.0.5", "plc-a.factory.lan", "fe80::1"):
        assert ModbusSettings.model_validate({"host": host, "delay_ms": 500}).host == host
    # a beat 1e300 ms off was one the worker could not wait for; a back-off as long left a PLC back on the line
    # unreached
    with pytest.raises(ValidationError, match="less than or equal to 60000"):
        ModbusSettings.model_validate({"heartbeat": {"address": 100, "period_ms": 1e300}, "delay_ms": 500})
    with pytest.raises(ValidationError, match="less than or equal to 60000"):
        ModbusSettings.model_validate({"reconnect_max_ms": 1e300, "delay_ms": 500})
    # the port failed to open at every reject ("invalid baudrate"), each an alarm
    with pytest.raises(ValidationError, match="less than or equal to 12000000"):
        ModbusSettings.model_validate({"transport": "rtu", "serial_port": "/dev/ttyUSB0", "baudrate": 10**20,
                                       "delay_ms": 500})
    # no device answers a broadcast: each reject would wait for an answer that never comes
    with pytest.raises(ValidationError, match="unit 0 is the RTU broadcast address"):
        ModbusSettings.model_validate({"transport": "rtu", "serial_port": "/dev/ttyUSB0", "unit": 0, "delay_ms": 500})
    assert ModbusSettings.model_validate({"transport": "tcp", "unit": 0, "delay_ms": 500}).unit == 0
    with pytest.raises(ValidationError, match="Extra inputs"):
        ModbusSettings.model_validate({"hots": "plc", "delay_ms": 500})
    with pytest.raises(ValidationError, match="pulse_ms applies to a coil"):
        ModbusSettings.model_validate({"on_reject": {"write": "register", "address": 1, "pulse_ms": 10}, "delay_ms": 500})
    # a PLC reads its coils once a scan: a high shorter than one could fall between two reads
    with pytest.raises(ValidationError, match="pulse_ms 0.5: shorter than the 20 ms a PLC needs to see the coil high"):
        ModbusSettings.model_validate({"on_reject": {"write": "coil", "pulse_ms": 0.5}, "delay_ms": 500})
    assert ModbusSettings.model_validate({"on_reject": {"write": "coil", "pulse_ms": 20}, "delay_ms": 500})
    # without a delay every command would be due at its part's capture, before the part is decided
    with pytest.raises(ValidationError, match="give the time from the camera to the actuator"):
        ModbusSettings.model_validate({})
    with pytest.raises(ValidationError, match="greater than 0"):
        ModbusSettings.model_validate({"delay_ms": 0})
    # 1e300 ms reached the socket as a time out of range, reported as a PLC that cannot be reached
    with pytest.raises(ValidationError, match="timeout_ms\n.*less than or equal to 10000"):
        ModbusSettings.model_validate({"delay_ms": 500, "timeout_ms": 1e300})


GATE = {"write": "coil", "address": 0, "pulse_ms": 100}


@pytest.mark.parametrize("settings, message", [
    ({"on_reject": GATE, "ready_coil": 0}, "on_reject writes coil 0, which is also ready_coil"),
    ({"on_pass": {"write": "coil", "address": 4}, "ready_coil": 4}, "on_pass writes coil 4, which is also ready_coil"),
    ({"on_reject": {"write": "counter", "address": 7}, "heartbeat": {"address": 7}},
     "on_reject writes register 7, which is also heartbeat.address"),
    ({"on_reject": GATE, "on_pass": GATE}, "could not tell a pass from a reject"),
    ({"on_reject": {"write": "counter", "address": 2}, "on_pass": {"write": "register", "address": 2, "value": 9}},
     "could not tell a pass from a reject"),
    ({"on_reject": GATE, "on_pass": {"write": "coil", "address": 0, "value": 0}}, "cut short the pulse"),
])
def test_two_signals_on_one_address_are_refused(settings, message):
    from pydantic import ValidationError

    with pytest.raises(ValidationError, match=message):
        ModbusSettings.model_validate({"delay_ms": 500, **settings})


@pytest.mark.parametrize("settings", [
    # one register whose value says which: a level the PLC reads at its own pace
    {"on_reject": {"write": "register", "address": 3, "value": 1},
     "on_pass": {"write": "register", "address": 3, "value": 2}},
    # coil 0 and register 0 are different tables
    {"on_reject": GATE, "on_pass": {"write": "register", "address": 0, "value": 2}, "heartbeat": {"address": 1},
     "ready_coil": 1},
])
def test_signals_the_plc_can_tell_apart_are_accepted(settings):
    ModbusSettings.model_validate({"delay_ms": 500, **settings})


def test_registered_as_output_plugin():
    from core.registry import default_registry

    plugin = default_registry().get("output", "modbus")
    assert plugin.spec.settings_model is ModbusSettings


# ------------------------------------------------------------------ Modbus RTU over a pty pair
def test_modbus_rtu_over_a_serial_line(pty_pair):
    plc_end, our_end = pty_pair
    sim = plc_sim.serve_rtu_in_thread(plc_end, on_change=None, baudrate=38400)
    try:
        out = ModbusOutput(ModbusSettings.model_validate({
            "transport": "rtu", "serial_port": our_end, "baudrate": 38400, "unit": 2, "delay_ms": 200,
            "timeout_ms": 300, "on_reject": {"write": "coil", "address": 4, "pulse_ms": 80}}))
        p = part(1)
        out.submit(p)
        events = out.close(timeout_s=3)
    finally:
        sim.stop()
    on = [w for w in sim.writes if w.table == "coil" and w.address == 4]
    assert [w.value for w in on] == [0, 1, 0]  # at rest on connecting, then the pulse
    assert abs(on[1].timestamp - (p.timestamp + 0.2)) < TOL_S
    assert [e.outcome for e in events_of(events)] == ["delivered", "delivered", "delivered"]
    assert not events_of(events, Alarm)


# ------------------------------------------------------------------ the actuator's state over a cut link
def test_a_link_cut_during_a_pulse_is_an_alarm_and_the_coil_is_reset_before_the_next_reject(sim, port):
    """The cable is pulled while the reject coil is on: its release cannot be sent, which is an alarm naming
    the part; once the PLC answers again the coil is put back at rest, so the next reject is a real rising
    edge (a coil left at 1 would see none, and its reject would count as delivered)."""
    from sim.tcp_proxy import TcpProxy

    with TcpProxy(port) as proxy:
        out = output(proxy.port, delay_ms=100, max_late_ms=100, on_reject={"write": "coil", "address": 0, "pulse_ms": 400})
        first = part(1)
        out.submit(first)
        events, deadline = [], time.monotonic() + 2
        while not any(e.part_id == first.part_id and e.outcome == "delivered" for e in events_of(events)):
            assert time.monotonic() < deadline, events
            time.sleep(0.01)
            events += out.poll()
        assert sim.coil(0) == 1
        proxy.cut()  # mid-pulse, its rising edge confirmed: the release cannot reach the PLC within its second
        time.sleep(1.8)
        events += out.poll()
        assert sim.coil(0) == 1  # what a plant would now have: the gate held open
        proxy.restore()
        # due after the link's next try (its backoff reaches 200 ms) and the rest write: queued while the link is
        # still down, as a line's next reject would be, without racing the reconnection
        second = part(2, t=time.time() + 0.5)
        out.submit(second)
        events += out.close(timeout_s=3)
    alarms = events_of(events, Alarm)
    release = [a for a in alarms if a.cause == "release"]
    assert len(release) == 1 and release[0].part_id == first.part_id and "may have stayed on" in release[0].message
    writes = [w.value for w in sim.writes if w.table == "coil" and w.address == 0]
    assert writes[:2] == [0, 1]  # at rest, the first pulse's rising edge
    assert writes[2:] == [0, 1, 0]  # after the cut: back at rest, the second reject's rising edge, its release
    delivered = [e for e in events_of(events) if e.part_id == second.part_id and "(pulse " in e.command]
    assert [e.outcome for e in delivered] == ["delivered"] and sim.coil(0) == 0


def wait_for(condition, timeout_s: float = 3.0) -> bool:
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if condition():
            return True
        time.sleep(0.01)
    return condition()


class TestHold:
    """A stalled inspection (the engine's watchdog) holds the output: the line is told it is not ready."""

    def test_hold_drops_the_ready_coil_and_stops_the_heartbeat_release_restores_both(self, sim, port):
        out = output(port, ready_coil=5, heartbeat={"address": 100, "period_ms": 50})
        assert wait_for(lambda: sim.coil(5) == 1 and sim.register(100) >= 2)
        out.hold("frame 000007 stuck in stereo")
        assert wait_for(lambda: sim.coil(5) == 0)
        beat = sim.register(100)
        time.sleep(0.3)  # six periods: a live heartbeat would have moved
        assert sim.register(100) == beat and sim.coil(5) == 0
        out.release()
        assert wait_for(lambda: sim.coil(5) == 1 and sim.register(100) > beat)
        commands = [e.command for e in events_of(out.close(timeout_s=2))]
        assert commands.count("write_coil 5 = 0 unit 1 (system stopped)") == 2  # the hold, and the close

    def test_rejects_still_fire_while_held(self, sim, port):
        out = output(port, ready_coil=5, delay_ms=200)
        out.hold("stalled")
        out.submit(part(1))
        events = out.close(timeout_s=2)
        assert len(coil_on_times(sim)) == 1 and not events_of(events, Alarm)

    def test_a_link_that_comes_back_while_held_hears_not_ready(self, port):
        out = output(port, ready_coil=5)
        out.hold("stalled")
        sim = plc_sim.serve_in_thread(HOST, port, on_change=None)
        try:
            assert wait_for(lambda: out.scheduler.connected)
            time.sleep(0.1)
            assert sim.coil(5) == 0 and not [w for w in sim.writes if w.table == "coil" and w.address == 5 and w.value == 1]
            out.close(timeout_s=2)
        finally:
            sim.stop()
