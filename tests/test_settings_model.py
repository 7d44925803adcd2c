"""core/settings_model.py: a YAML boolean is not taken for the number 1 or 0 by any settings model."""
from __future__ import annotations

from typing import Any, Literal

import pytest
from pydantic import ValidationError

from core.settings_model import Settings, takes_bool
from plugins.modbus_output import ModbusSettings


class TestTakesBool:
    @pytest.mark.parametrize("annotation", [bool, bool | None, Any, int | bool, Literal["auto", True]])
    def test_types_that_hold_a_boolean(self, annotation):
        assert takes_bool(annotation)

    @pytest.mark.parametrize("annotation", [int, float, float | None, str, Literal["auto", "cpu"], tuple[float, float]])
    def test_types_that_do_not(self, annotation):
        assert not takes_bool(annotation)


class _Example(Settings):
    port: int = 502
    limit: float | None = None
    flag: bool = False
    pair: tuple[float, float] | None = None
    anything: Any = None


class TestSettings:
    @pytest.mark.parametrize("key", ["port", "limit"])
    @pytest.mark.parametrize("value", [True, False])
    def test_a_boolean_for_a_number_is_refused(self, key, value):
        with pytest.raises(ValidationError, match="a boolean where a number or text is expected"):
            _Example(**{key: value})

    def test_a_boolean_inside_a_pair_of_numbers_is_refused(self):
        with pytest.raises(ValidationError, match="item 1: a boolean"):
            _Example(pair=[350, True])

    def test_booleans_where_they_belong_and_numbers_are_taken(self):
        ok = _Example(port=5020, limit=1, flag=True, pair=[350, 500], anything=True)
        assert (ok.port, ok.limit, ok.flag, ok.pair, ok.anything) == (5020, 1.0, True, (350.0, 500.0), True)

    def test_unknown_keys_are_refused(self):
        with pytest.raises(ValidationError, match="Extra inputs are not permitted"):
            _Example(prot=502)

    def test_a_plugins_settings_refuse_the_broadcast_unit_written_as_false(self):
        # unit 0 is Modbus's broadcast: every device on the line would act on the reject
        base = {"host": "127.0.0.1", "delay_ms": 100}
        assert ModbusSettings(**base, unit=1).unit == 1
        with pytest.raises(ValidationError, match="unit\n.*a boolean where a number"):
            ModbusSettings(**base, unit=False)
