"""The format strings of the log and serial outputs: refused with the recipe, filled in per part."""
from __future__ import annotations

import pytest
from pydantic import ValidationError

from core.types import PartResult, Status, Verdict
from plugins.command_format import checked_format, command_text
from plugins.log_output import LogSettings
from plugins.serial_output import SerialSettings


def part(status: Status = Status.REJECT) -> PartResult:
    return PartResult("P0042", "000042", 42, 0.0, Verdict(status, []))


class TestCheckedFormat:
    @pytest.mark.parametrize("fmt", ["REJECT {part_id}", "{status} {frame_id} {index:05d}", "REJECT", None])
    def test_formats_of_the_parts_fields_pass_unchanged(self, fmt):
        assert checked_format(fmt) == fmt

    @pytest.mark.parametrize("fmt, why", [
        ("REJECT {part}", "unknown field {part}"),
        ("REJECT {0}", "Replacement index 0"),
        ("REJECT {part_id", "expected '}'"),
        ("REJECT }", "Single '}'"),
        ("{part_id.name}", "no attribute"),
        ("{index[0]}", "not subscriptable"),
        ("{index:q}", "Unknown format code"),
    ])
    def test_anything_else_is_refused_naming_the_fields(self, fmt, why):
        with pytest.raises(ValueError, match="bad format") as info:
            checked_format(fmt)
        assert why in str(info.value) and "{part_id}, {status}, {frame_id}, {index}" in str(info.value)


class TestCommandText:
    def test_every_field_is_the_parts(self):
        assert command_text("{status} {part_id} {frame_id} {index:04d}", part()) == "REJECT P0042 000042 0042"
        assert command_text("PASS {part_id}", part(Status.PASS)) == "PASS P0042"


@pytest.mark.parametrize("settings_model, base", [(LogSettings, {}), (SerialSettings, {"port": "loop://"})])
@pytest.mark.parametrize("key", ["reject_format", "pass_format"])
def test_both_outputs_refuse_a_bad_format_in_their_settings(settings_model, base, key):
    with pytest.raises(ValidationError, match="unknown field {partid}"):
        settings_model.model_validate({**base, key: "REJECT {partid}"})
