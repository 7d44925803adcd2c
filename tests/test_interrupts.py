"""``core.interrupts``: a Ctrl-C is a Ctrl-C, however a stage's code hands it back."""
from __future__ import annotations

import os
import signal
import threading
import time

import numpy as np
import pytest
from numba import njit

from core.interrupts import raise_if_interrupted


def _raised(make):
    try:
        make()
    except BaseException as exc:  # noqa: B036 - what each case raises, whatever it is
        return exc
    raise AssertionError("nothing raised")


def _from(outer, inner):
    def make():
        try:
            raise inner
        except BaseException as exc:
            raise outer from exc
    return make


class TestRaiseIfInterrupted:
    def test_a_stage_failure_is_left_to_the_caller(self):
        raise_if_interrupted(_raised(_from(ValueError("no plate"), OSError("disk"))))

    def test_an_interrupt_as_the_cause_is_raised(self):
        exc = _raised(_from(SystemError("returned a result with an exception set"), KeyboardInterrupt()))
        with pytest.raises(KeyboardInterrupt) as raised:
            raise_if_interrupted(exc)
        assert raised.value.__cause__ is exc

    def test_an_interrupt_during_the_handling_of_another_error_is_raised(self):
        def make():
            try:
                raise KeyboardInterrupt
            except KeyboardInterrupt:
                raise RuntimeError("cleanup failed")  # __context__, not __cause__
        with pytest.raises(KeyboardInterrupt):
            raise_if_interrupted(_raised(make))

    def test_an_exception_chain_that_loops_ends(self):
        a, b = ValueError("a"), ValueError("b")
        a.__context__, b.__context__ = b, a
        raise_if_interrupted(a)


@njit(nogil=True)
def _busy(started, n):
    started[0] = 1
    total = 0.0
    for i in range(n):
        total += np.sqrt(i + total % 3)
    return np.zeros(2), total  # a tuple is boxed on the way back, which is where the signal shows


class TestNumbaInterrupted:
    """Why the helper exists: SIGINT inside a nogil numba function, as a real Ctrl-C lands in the depth stage."""

    def test_comes_out_as_a_system_error_caused_by_the_interrupt(self):
        _busy(np.zeros(1, np.int64), 10)  # compiled before the clock starts
        started = np.zeros(1, np.int64)
        armed, late = [True], []

        def on_sigint(number, frame):  # Python's own raises too; a late one must not end the whole session
            if not armed[0]:
                late.append(number)
                return
            raise KeyboardInterrupt

        def interrupt_once_inside():
            while not started[0]:
                time.sleep(0.001)
            os.kill(os.getpid(), signal.SIGINT)

        previous = signal.signal(signal.SIGINT, on_sigint)
        try:
            sender = threading.Thread(target=interrupt_once_inside)
            sender.start()
            exc = _raised(lambda: _busy(started, 50_000_000))
            armed[0] = False
            sender.join()
        finally:
            signal.signal(signal.SIGINT, previous)
        assert not late, "the signal came after the kernel had returned"
        assert isinstance(exc, SystemError) and isinstance(exc.__cause__, KeyboardInterrupt), repr(exc)
        with pytest.raises(KeyboardInterrupt):
            raise_if_interrupted(exc)


class TestCommandLine:
    """``inspect eval depth`` and the other commands that run the kernels outside the run loop."""

    @staticmethod
    def _main_with(monkeypatch, raises):
        import click

        from core import cli

        @click.group()
        def group():
            pass

        @group.command()
        def measure():
            raise raises

        monkeypatch.setattr(cli, "_build", lambda: group)
        with pytest.raises(SystemExit) as exited:
            cli.main(["measure"])
        return exited.value.code

    def test_ctrl_c_inside_a_kernel_is_aborted_as_any_ctrl_c(self, monkeypatch, capsys):
        interrupted = _raised(_from(SystemError("returned a result with an exception set"), KeyboardInterrupt()))
        assert self._main_with(monkeypatch, interrupted) == 1
        assert capsys.readouterr().err.strip() == "Aborted!"

    def test_any_other_system_error_is_left_as_it_is(self, monkeypatch):
        with pytest.raises(SystemError, match="a bug"):
            self._main_with(monkeypatch, SystemError("a bug"))
