"""The line `inspect run` prints for each part."""
from types import SimpleNamespace

from core.commands.inspection import part_line
from core.types import DefectMeasurement, Detection, PartResult, Status, Verdict


def _part(*measurements, reasons=()):
    return SimpleNamespace(part=PartResult("R1-000003", "000003", 3, 0.0, Verdict(Status.REJECT, list(reasons)),
                                           list(measurements)))


def test_a_defect_measured_along_a_groove_says_so():
    groove = DefectMeasurement(Detection("scratches", 0.91, (10, 10, 60, 50)), 421.3, 1.83, 1.0, 0.5, 120.0,
                               note="measured along a groove across the box, 38 degrees from its rows",
                               distance_sigma_mm=0.2, deviation_sigma_mm=0.23, method="surface")
    line = part_line(_part(groove))
    assert "scratches 0.91 Z=421.3±0.2mm dev=+1.83±0.23mm (measured along a groove across the box, 38 degrees" in line


def test_an_unavailable_deviation_s_note_is_the_reason_alone():
    why = "deviation unavailable: the surface fit did not settle"
    missing = DefectMeasurement(Detection("inclusion", 0.7, (10, 10, 60, 50)), 421.3, None, 1.0, 0.5, 120.0, note=why)
    line = part_line(_part(missing, reasons=[f"inclusion (0.70): rule 'deviation_mm > 1' needs deviation_mm, {why}"]))
    assert line.count(why) == 1 and "dev=n/a  <- " in line
