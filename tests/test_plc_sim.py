"""The PLC simulator: a real pymodbus server, in a thread and as ``inspect plc-sim``."""
from __future__ import annotations

import os
import re
import subprocess
import sys
import time
from pathlib import Path

import pytest
from conftest import start_pty_pair

from drivers import plc_sim
from drivers.modbus_link import ModbusLink, ModbusWrite

LINE = re.compile(r"^\d\d:\d\d:\d\d\.\d{3} (unit \d+ )?(coil|register) \d+ -> \d+$")
ROOT = Path(__file__).resolve().parents[1]


def test_serve_in_thread_reports_changes_and_stops():
    port = plc_sim.free_port()
    assert not plc_sim.is_listening("127.0.0.1", port)
    lines: list[str] = []
    sim = plc_sim.serve_in_thread("127.0.0.1", port, on_change=lines.append)
    try:
        assert plc_sim.is_listening("127.0.0.1", port)
        link = ModbusLink("tcp", "127.0.0.1", port)
        link.connect()
        link.send(ModbusWrite("coil", 0, 1))
        link.send(ModbusWrite("coil", 0, 1))  # no change: no line
        link.send(ModbusWrite("register", 12, 345))
        link.send(ModbusWrite("coil", 0, 0))
        assert link.read("coil", 0, 1) == [0] and link.read("register", 12) == [345]
        link.close()
    finally:
        sim.stop()
    assert not plc_sim.is_listening("127.0.0.1", port)
    assert all(LINE.match(line) for line in lines), lines
    assert [line[13:] for line in lines] == ["coil 0 -> 1", "register 12 -> 345", "coil 0 -> 0"]
    assert [(w.table, w.address, w.value) for w in sim.writes] == [("coil", 0, 1), ("coil", 0, 1), ("register", 12, 345), ("coil", 0, 0)]


# In a fresh interpreter: the first import of pymodbus is what raced. Before the drivers imported it themselves,
# every run of this failed (a deadlock or a module found half-initialised).
_FIRST_USE_IN_TWO_THREADS = """
import threading
from drivers import plc_sim
from drivers.modbus_link import ModbusLink
port = plc_sim.free_port()
barrier, errors = threading.Barrier(2), []
def serve():
    barrier.wait()
    try:
        plc_sim.serve_in_thread("127.0.0.1", port, on_change=None).stop()
    except Exception as exc:
        errors.append(repr(exc))
def connect():
    barrier.wait()
    try:
        ModbusLink(transport="tcp", host="127.0.0.1", port=port)._make_client()
    except Exception as exc:
        errors.append(repr(exc))
threads = [threading.Thread(target=serve), threading.Thread(target=connect)]
for t in threads:
    t.start()
for t in threads:
    t.join()
print(errors)
"""


@pytest.mark.parametrize("attempt", range(3))
def test_the_simulator_and_a_link_can_start_at_once_in_two_threads(attempt):
    """`--plc-sim` serves from the same process whose outputs connect from their own threads."""
    out = subprocess.run([sys.executable, "-c", _FIRST_USE_IN_TWO_THREADS], capture_output=True, text=True,
                         cwd=ROOT, timeout=60)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]"


def test_port_in_use_is_an_error():
    port = plc_sim.free_port()
    with plc_sim.serve_in_thread("127.0.0.1", port, on_change=None):
        with pytest.raises(OSError, match=f"cannot serve on 127.0.0.1:{port}"):
            plc_sim.serve_in_thread("127.0.0.1", port, on_change=None)


def _inspect(*args: str, **kw) -> subprocess.Popen:
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    return subprocess.Popen([sys.executable, "-c", "from core.cli import main; main()", *args], cwd=ROOT, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, **kw)


def test_cli_prints_each_change_with_a_timestamp():
    port = plc_sim.free_port()
    proc = _inspect("plc-sim", "--port", str(port), "--duration", "1.5")
    try:
        deadline = time.monotonic() + 20
        while not plc_sim.is_listening("127.0.0.1", port):
            assert proc.poll() is None, proc.stderr.read()
            assert time.monotonic() < deadline, "plc-sim did not start"
            time.sleep(0.1)
        link = ModbusLink("tcp", "127.0.0.1", port)
        link.connect()
        link.send(ModbusWrite("coil", 0, 1, unit=1))
        link.send(ModbusWrite("coil", 0, 0, unit=1))
        link.close()
        out, err = proc.communicate(timeout=20)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, err
    changes = [line for line in out.splitlines() if LINE.match(line)]
    assert [c[13:] for c in changes] == ["coil 0 -> 1", "coil 0 -> 0"]
    assert f"PLC simulator on tcp 127.0.0.1:{port}" in out and "2 writes received" in out


def test_cli_port_in_use_is_one_line_error():
    from click.testing import CliRunner

    from core.commands.hardware import plc_sim_command

    port = plc_sim.free_port()
    with plc_sim.serve_in_thread("127.0.0.1", port, on_change=None):
        result = CliRunner().invoke(plc_sim_command, ["--port", str(port), "--duration", "1"])
    assert result.exit_code == 2
    assert result.stderr.startswith("error: PLC simulator cannot serve on") and "Traceback" not in result.output
    assert len(result.stderr.strip().splitlines()) == 1


def test_cli_names_the_serial_port_it_cannot_serve_on_not_the_tcp_address(tmp_path):
    from click.testing import CliRunner

    from core.commands.hardware import plc_sim_command

    missing = str(tmp_path / "no-such-tty")
    result = CliRunner().invoke(plc_sim_command, ["--port", str(plc_sim.free_port()), "--rtu", missing,
                                                  "--duration", "1"])
    assert result.exit_code == 2
    assert result.stderr.startswith(f"error: PLC simulator cannot serve on {missing}: ")
    assert len(result.stderr.strip().splitlines()) == 1
    # "Python int too large to convert to C long", from the serial layer, once it had started
    result = CliRunner().invoke(plc_sim_command, ["--port", "0", "--rtu", missing, "--baudrate", str(10**20)])
    assert result.exit_code == 2 and "'--baudrate': 100000000000000000000 is not in the range 1<=x<=12000000" in \
        result.stderr


def test_cli_serves_modbus_rtu_on_a_serial_port(tmp_path):
    pair, a, b = start_pty_pair(tmp_path)
    try:
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        proc = subprocess.Popen(
            [sys.executable, "-c", "from core.commands.hardware import plc_sim_command; plc_sim_command()",
             "--port", "0", "--rtu", str(a), "--baudrate", "38400", "--duration", "2"],
            cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        first = proc.stdout.readline()  # printed once the server runs
        assert f"PLC simulator on rtu {a}" in first, first + proc.stderr.read()
        link = ModbusLink("rtu", serial_port=str(b), baudrate=38400, timeout_s=0.5)
        link.connect()
        link.send(ModbusWrite("coil", 3, 1, unit=7))
        link.close()
        out, err = proc.communicate(timeout=20)
    finally:
        pair.terminate()
        pair.wait(5)
    assert proc.returncode == 0, err
    assert [line[13:] for line in out.splitlines() if LINE.match(line)] == ["unit 7 coil 3 -> 1"]
