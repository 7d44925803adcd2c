"""Invalid recipes: one line naming file, line and key path; exit 2; no traceback."""
from __future__ import annotations

import os
import re

import pytest
from conftest import ROOT, cli, cli_here, write_recipe

from core.commands.inspection import recipe_warnings
from core.recipe import RecipeError, load_recipe

GOOD = """\
name: t
camera:
  plugin: replay
  settings:
    path: seq
stereo:
  backend: opencv_sgbm
  max_disparity: 64
detector:
  plugin: yolov8
decision:
  rules:
    - {class: any, quantity: deviation_mm, op: ">", threshold: 1.0}
outputs:
  - plugin: log
verify:
  path: MASTERS
""".replace("MASTERS", str(ROOT / "sim_fixtures" / "steel_plate_masters"))  # named, as a line's recipe names them
# (validate reads their labels only; run would inspect them, which 64 px of disparity cannot reach)


@pytest.fixture
def recipe_dir(tmp_path, plane_sequence):
    plane_sequence([0.0])
    return tmp_path


def _error(recipe_dir, text, overrides=()):
    path = write_recipe(recipe_dir / "r.yaml", text)
    with pytest.raises(RecipeError) as info:
        load_recipe(path, overrides)
    message = str(info.value)
    assert "\n" not in message
    assert message.startswith(str(path))
    return message


def test_good_recipe_loads(recipe_dir):
    loaded = load_recipe(write_recipe(recipe_dir / "r.yaml", GOOD))
    assert loaded.recipe.stereo.max_disparity == 64
    assert loaded.plugin_settings["camera"]["path"] == str((recipe_dir / "seq").resolve())


def test_unknown_key_names_line_and_path(recipe_dir):
    message = _error(recipe_dir, GOOD.replace("  max_disparity: 64", "  max_disparty: 64"))
    assert re.search(r"r\.yaml:8: stereo\.max_disparty: unknown key; did you mean 'max_disparity'\?", message), message


@pytest.mark.parametrize("old, new, hint", [
    ("name: t", "name: t\nthread: 2", "thread: unknown key; did you mean 'threads'?"),  # top level
    ("{class: any", "{clas: any", "decision.rules.0.clas: unknown key; did you mean 'class'?"),  # a list's, aliased
    ("outputs:", "depth: {ring_widht: 4}\noutputs:", "depth.ring_widht: unknown key; did you mean 'ring_width_px'?"),
    ("outputs:", "depth: {zzz: 4}\noutputs:", "depth.zzz: unknown key"),  # nothing close: no guess
])
def test_an_unknown_key_suggests_the_closest_known_one(recipe_dir, old, new, hint):
    message = _error(recipe_dir, GOOD.replace(old, new, 1))
    assert message.endswith(hint), message


def test_wrong_type(recipe_dir):
    message = _error(recipe_dir, GOOD.replace("max_disparity: 64", "max_disparity: lots"))
    assert ":8: stereo.max_disparity:" in message and "'lots'" in message


def test_a_section_that_is_not_a_mapping_lists_its_keys(recipe_dir):
    message = _error(recipe_dir, GOOD, ["camera.image_check=5"])
    assert "camera.image_check: should be a mapping of min_mean_grey, max_saturated, min_texture (got 5)" in message


def test_out_of_range(recipe_dir):
    message = _error(recipe_dir, GOOD.replace("threshold: 1.0}", "threshold: 1.0}\n    - {class: any, quantity: depth, op: '>', threshold: 1}"))
    assert "decision.rules.1.quantity" in message and ":14:" in message


@pytest.mark.parametrize("setting, says", [
    # a share of the box that takes in the defect's walls reads it shallower: defective plates passed
    ("depth.inner_fraction=0.8", "depth.inner_fraction: Input should be less than or equal to 0.6 (got 0.8)"),
    ("depth.roi=box", "depth.roi: unknown key"),  # the whole box: no longer a setting
    # a disparity noise the map does not have proves what it cannot tell
    ("depth.disparity_noise_px=0.05", "depth.disparity_noise_px: Input should be greater than or equal to 0.25 (got 0.05)"),
])
def test_a_depth_setting_that_passed_defective_plates_is_refused(recipe_dir, setting, says):
    assert _error(recipe_dir, GOOD, [setting]).endswith(says)


def test_a_watchdog_that_would_never_bark_is_refused(recipe_dir):
    # 1e300 s turned the stall alarm off (and killed the watch's thread with an OverflowError)
    assert _error(recipe_dir, GOOD, ["watchdog_s=1e300"]).endswith(
        "watchdog_s: Input should be less than or equal to 600 (got '1e300')")


def test_a_page_rate_a_browser_cannot_wait_for_is_refused(recipe_dir):
    assert _error(recipe_dir, GOOD, ["view.max_fps=1e-300"]).endswith(
        "view.max_fps: Input should be greater than or equal to 0.1 (got '1e-300')")


def test_unknown_plugin_lists_known_ones(recipe_dir):
    message = _error(recipe_dir, GOOD.replace("plugin: yolov8", "plugin: yolo9"))
    assert ":10: detector.plugin: unknown detector plugin 'yolo9'; did you mean 'yolov8'? known:" in message
    message = _error(recipe_dir, GOOD.replace("plugin: yolov8", "plugin: detr"))
    assert message.endswith(":10: detector.plugin: unknown detector plugin 'detr'; known: yolov8")


@pytest.mark.parametrize("setting, says", [
    # the value given is said even where the allowed ones hold it ('surface' holds 'surfac', 0.05 holds 0)
    ("depth.method=surfac", "depth.method: Input should be 'surface' or 'disparity' (got 'surfac')"),
    ("stereo.scale=0", "stereo.scale: Input should be greater than 0.05 (got 0)"),
])
def test_the_value_given_is_said_where_the_allowed_ones_contain_it(recipe_dir, setting, says):
    assert _error(recipe_dir, GOOD, [setting]).endswith(says)


def test_missing_weights_file(recipe_dir):
    message = _error(recipe_dir, GOOD.replace("plugin: yolov8", "plugin: yolov8\n  weights: models/nope.pt"))
    assert "detector.weights: weights file not found" in message and "nope.pt" in message


def test_missing_sequence_folder(recipe_dir):
    message = _error(recipe_dir, GOOD.replace("path: seq", "path: no_such_seq"))
    assert ":5: camera.settings.path: sequence folder not found" in message


def test_yaml_syntax_error(recipe_dir):
    message = _error(recipe_dir, GOOD.replace("  backend: opencv_sgbm", "  backend: [opencv_sgbm"))
    assert "YAML syntax error" in message and re.search(r"r\.yaml:\d+:", message)


def test_a_key_given_twice_is_an_error_naming_both_lines(recipe_dir):
    text = GOOD.replace('threshold: 1.0}', 'threshold: 1.0}\n    - {class: any, quantity: deviation_mm, op: ">", '
                        'threshold: 1.0, threshold: 9.0}').replace("name: t", "name: t\nname: u")
    message = _error(recipe_dir, text)
    assert re.search(r"r\.yaml:2: name: given twice \(first at line 1\)", message), message
    message = _error(recipe_dir, text.replace("name: u\n", ""))
    assert "decision.rules.1.threshold: given twice" in message, message


@pytest.mark.parametrize("value", [".nan", ".inf", "-.inf"])
def test_a_threshold_that_is_not_a_finite_number_is_an_error(recipe_dir, value):
    # every comparison with NaN is false: such a rule would never reject
    message = _error(recipe_dir, GOOD.replace("threshold: 1.0", f"threshold: {value}"))
    assert ":13: decision.rules.0.threshold: must be a finite number" in message, message


@pytest.mark.parametrize("value", ["nan", "NaN", "inf", "-infinity", "1e400", "'nan'"])
def test_a_threshold_spelt_as_text_that_reads_as_nan_or_infinity_is_an_error(recipe_dir, value):
    # not YAML floats but text, which pydantic would read as the number: a rule that never rejects
    message = _error(recipe_dir, GOOD.replace("threshold: 1.0", f"threshold: {value}"))
    assert ":13: decision.rules.0.threshold: Input should be a finite number" in message, message


def test_a_plugin_setting_spelt_as_nan_is_an_error(recipe_dir):
    message = _error(recipe_dir, GOOD.replace("    path: seq", "    path: seq\n    rate_fps: nan"))
    assert ":6: camera.settings.rate_fps: Input should be a finite number" in message, message


class _PlainModelOutput:
    """A third-party output whose settings model is pydantic's own BaseModel, which reads "nan" as a number."""

    @staticmethod
    def spec():
        from pydantic import BaseModel

        from core.contracts import PluginSpec

        class Plain(BaseModel):
            limits: tuple[float, float] = (0.0, 1.0)

        return PluginSpec("plain", "output", lambda s, ctx: None, settings_model=Plain)

    from core.hookspecs import hookimpl

    @hookimpl
    def stereo_inspect_outputs(self):
        return [self.spec()]


def test_a_third_party_model_on_plain_pydantic_may_not_take_nan_either(recipe_dir):
    from core.registry import Registry, make_manager

    registry = Registry(make_manager((_PlainModelOutput(),)))
    path = write_recipe(recipe_dir / "r.yaml", GOOD.replace("  - plugin: log", "  - plugin: plain\n    settings: "
                                                                             "{limits: [0, nan]}"))
    with pytest.raises(RecipeError, match=r"r\.yaml:16: outputs\.0\.settings\.limits\.1: must be a finite number "
                                          r"\(got nan\)"):
        load_recipe(path, registry=registry)
    load_recipe(path, ["outputs.0.settings.limits=[0, 2]"], registry=registry)


def test_an_alias_that_holds_itself_or_expands_without_bound_is_an_error(recipe_dir):
    message = _error(recipe_dir, GOOD + "extra: &a [*a]\n")
    assert re.search(r"r\.yaml:\d+: an alias \(\*name\) refers to a node that holds it", message), message
    bomb = "".join(f"x{i}: &x{i} [" + ", ".join([f"*x{i - 1}"] * 9) + "]\n" for i in range(1, 10))
    message = _error(recipe_dir, GOOD + "x0: &x0 [1, 2, 3, 4, 5, 6, 7, 8, 9]\n" + bomb)
    assert "the document's aliases (*name) expand it beyond 100,000 values" in message, message


def test_a_number_yaml_would_read_as_octal_or_base_60_is_an_error_naming_its_key(recipe_dir):
    # YAML 1.1 reads 010 as 8: an address written with a leading zero would pulse another coil
    text = GOOD.replace("  - plugin: log", "  - plugin: log\n    settings: {file: r.log, delay_ms: 010}")
    message = _error(recipe_dir, text)
    assert ":16: outputs.0.settings.delay_ms: 010: YAML reads a leading zero as octal, 8; write 10" in message, message
    message = _error(recipe_dir, GOOD.replace("    path: seq", "    path: seq\n    rate_fps: 1:30"))
    assert ":6: camera.settings.rate_fps: 1:30: YAML reads this as the base-60 number 90" in message, message
    with pytest.raises(RecipeError, match="--set stereo.max_disparity=064: 064: YAML reads a leading zero as octal, 52"):
        load_recipe(write_recipe(recipe_dir / "r.yaml", GOOD), ["stereo.max_disparity=064"])
    quoted = load_recipe(write_recipe(recipe_dir / "r.yaml", GOOD), ["stereo.max_disparity='064'"])
    assert quoted.recipe.stereo.max_disparity == 64
    with pytest.raises(RecipeError, match=r"--set stereo.settings=\{p1: 010\}: p1: 010: YAML reads a leading zero"):
        load_recipe(write_recipe(recipe_dir / "r.yaml", GOOD), ["stereo.settings={p1: 010}"])
    with pytest.raises(RecipeError, match=r"--set stereo.settings=\{p1: 1, p1: 2\}: p1: given twice"):
        load_recipe(write_recipe(recipe_dir / "r.yaml", GOOD), ["stereo.settings={p1: 1, p1: 2}"])


@pytest.mark.parametrize("where, text, key", [
    # pydantic reads true as 1 and false as 0: the broadcast unit, coil 1, a 1 mm limit
    ("    path: seq", "    path: seq\n    rate_fps: yes", ":6: camera.settings.rate_fps"),
    ("threshold: 1.0", "threshold: on", ":13: decision.rules.0.threshold"),
    ("max_disparity: 64", "max_disparity: true", ":8: stereo.max_disparity"),
    ("max_disparity: 64", "working_distance_mm: [true, 600]", ":8: stereo.working_distance_mm: item 0"),
])
def test_a_boolean_where_a_number_belongs_is_an_error_not_one_or_zero(recipe_dir, where, text, key):
    message = _error(recipe_dir, GOOD.replace(where, text))
    assert f"{key}: a boolean where a number or text is expected" in message, message


def test_a_boolean_setting_still_takes_a_boolean(recipe_dir):
    text = GOOD.replace("    path: seq", "    path: seq\n    loop: yes").replace("max_disparity: 64",
                                                                                "max_disparity: 64\n  concurrent: off")
    loaded = load_recipe(write_recipe(recipe_dir / "r.yaml", text))
    assert loaded.recipe.stereo.concurrent is False


def test_an_integer_too_long_to_read_is_an_error_naming_its_key(recipe_dir):
    message = _error(recipe_dir, GOOD.replace("max_disparity: 64", "max_disparity: 1" + "0" * 5000))
    assert ":8: stereo.max_disparity: 100000000000...: an integer of 5001 digits, more than can be read" in message


def test_a_working_distance_beyond_any_camera_is_an_error(recipe_dir):
    # 1e300 mm overflowed the depth resolution's square in validate's warnings: a traceback
    message = _error(recipe_dir, GOOD.replace("max_disparity: 64", "working_distance_mm: [350, 1e300]"))
    assert ":8: stereo.working_distance_mm: 1e+300 mm is farther than any stereo camera measures" in message, message


def test_an_empty_class_list_is_an_error_not_a_line_that_passes_everything(recipe_dir):
    message = _error(recipe_dir, GOOD.replace("plugin: yolov8", "plugin: yolov8\n  classes: []"))
    assert ":11: detector.classes: an empty list keeps no class" in message, message


def test_no_plugin_setting_or_override_may_be_nan(recipe_dir):
    message = _error(recipe_dir, GOOD.replace("    path: seq", "    path: seq\n    rate_fps: .nan"))
    assert ":6: camera.settings.rate_fps: must be a finite number (got nan)" in message, message
    message = _error(recipe_dir, GOOD, ["stereo.scale=.nan"])
    assert "(--set stereo.scale): stereo.scale: must be a finite number" in message, message


def test_a_recipe_not_in_utf8_names_its_line(recipe_dir):
    path = recipe_dir / "r.yaml"
    path.write_bytes(GOOD.replace("name: t", "name: t # caf\xe9").encode("latin-1"))
    with pytest.raises(RecipeError, match=r"r\.yaml:1: not UTF-8 text \(byte 0xe9\)"):
        load_recipe(path)


def test_a_byte_order_mark_is_read_past(recipe_dir):
    path = recipe_dir / "r.yaml"
    path.write_bytes(b"\xef\xbb\xbf" + GOOD.encode())
    assert load_recipe(path).recipe.name == "t"


def test_plugin_setting_typo(recipe_dir):
    message = _error(recipe_dir, GOOD.replace("    path: seq", "    path: seq\n    rate_fsp: 5"))
    assert ":6: camera.settings.rate_fsp: unknown key; did you mean 'rate_fps'?" in message


def test_a_search_range_wider_than_the_cameras_image_is_an_error(recipe_dir):
    message = _error(recipe_dir, GOOD.replace("max_disparity: 64", "max_disparity: 400"))
    assert ":8: stereo.max_disparity: 400 px of disparity does not fit the camera's 320 px wide image" in message


def test_a_working_distance_nearer_than_both_eyes_see_is_an_error_naming_the_nearest(recipe_dir):
    text = GOOD.replace("  max_disparity: 64", "  working_distance_mm: [5, 600]")
    message = _error(recipe_dir, text)
    assert ":8: stereo.working_distance_mm: the camera cannot see 5 mm with both eyes" in message, message
    nearest = int(re.search(r"the nearest it can match is (\d+) mm", message).group(1))
    assert load_recipe(write_recipe(recipe_dir / "ok.yaml", text.replace("[5, 600]", f"[{nearest}, 600]")))
    assert "cannot see" in _error(recipe_dir, text.replace("[5, 600]", f"[{nearest - 1}, 600]"))


def test_inconsistent_disparity_range(recipe_dir):
    message = _error(recipe_dir, GOOD.replace("max_disparity: 64", "max_disparity: 64\n  min_disparity: 80"))
    assert "stereo: max_disparity must be larger than min_disparity" in message


def test_set_override_applies_and_is_located(recipe_dir):
    path = write_recipe(recipe_dir / "r.yaml", GOOD)
    loaded = load_recipe(path, ["stereo.max_disparity=96", "outputs.0.settings.on_pass=true"])
    assert loaded.recipe.stereo.max_disparity == 96
    assert loaded.plugin_settings["outputs.0"]["on_pass"] is True
    message = _error(recipe_dir, GOOD, ["stereo.max_disparity=-3"])
    assert "(--set stereo.max_disparity): stereo.max_disparity:" in message


def test_a_key_under_a_section_given_whole_by_set_is_located_at_the_set_not_at_the_files_line():
    # the demo's line of stereo.settings holds other settings: pointing there sent the user to the wrong place
    with pytest.raises(RecipeError) as raised:
        load_recipe(ROOT / "recipes" / "steel_plate.yaml",
                    ["stereo={backend: torch_sgm, working_distance_mm: [350, 500], settings: {nope: 1}}"])
    assert str(raised.value).endswith("steel_plate.yaml (--set stereo): stereo.settings.nope: unknown key")


def test_a_key_given_by_an_option_of_its_own_is_located_at_that_option(recipe_dir, monkeypatch):
    path = write_recipe(recipe_dir / "r.yaml", GOOD)
    with pytest.raises(RecipeError) as raised:
        load_recipe(path, ["stereo.backend=torch_sgn"], options={"stereo.backend": "--backend"})
    assert str(raised.value).startswith(f"{path.resolve()} (--backend): stereo.backend: unknown stereo plugin")
    monkeypatch.setattr(os, "cpu_count", lambda: 2)
    warned = [w for w in recipe_warnings(load_recipe(path, ["threads=5"], options={"threads": "--threads"}))
              if "threads" in w]
    assert len(warned) == 1 and warned[0].startswith(f"{path.resolve()} (--threads): threads: warning: 5 threads")
    # the console script's own option, not a --set the user never typed
    result = cli_here("eval", "depth", str(ROOT / "sim_fixtures" / "steel_plate"), "--recipe", str(path),
                      "--backend", "torch_sgn")
    assert result.returncode == 2 and "(--backend): stereo.backend: unknown stereo plugin 'torch_sgn'" in result.stderr


def test_another_plugin_by_set_starts_from_its_own_settings():
    """The demo recipe's stereo settings are torch_sgm's: switching the backend leaves them behind, unless
    the command line gives the new one settings of its own."""

    demo = ROOT / "recipes" / "steel_plate.yaml"
    assert load_recipe(demo).plugin_settings["stereo"]["align"] == "none"
    sgbm = load_recipe(demo, ["stereo.backend=opencv_sgbm"])
    assert sgbm.recipe.stereo.backend == "opencv_sgbm" and "align" not in sgbm.plugin_settings["stereo"]
    assert load_recipe(demo, ["stereo.backend=opencv_sgbm", "stereo.settings.block_size=7"]).plugin_settings[
        "stereo"]["block_size"] == 7
    with pytest.raises(RecipeError, match="stereo.settings.align: unknown key"):
        load_recipe(demo, ["stereo.backend=opencv_sgbm", "stereo.settings.block_size=7", "stereo.settings.align=none"])


@pytest.mark.parametrize(
    "change",
    [
        ("  max_disparity: 64", "  max_disparty: 64"),
        ("max_disparity: 64", "max_disparity: lots"),
        ("plugin: yolov8", "plugin: yolo9"),
        ("plugin: yolov8", "plugin: yolov8\n  weights: nope.pt"),
        ("path: seq", "path: nope"),
        ("path: seq", 'path: "se\\nq"'),  # a line break in a value: written as its escape, on the one line
        ("  backend: opencv_sgbm", "  backend: [opencv_sgbm"),
        ("  - plugin: log", "  - plugin: log\n    settings: {reject_format: 'REJECT {part}'}"),  # not at the first reject
    ],
)
def test_cli_validate_exit_2_one_line(recipe_dir, change):
    path = write_recipe(recipe_dir / "r.yaml", GOOD.replace(*change))
    for command in ("validate", "run"):
        result = cli_here(command, str(path))
        assert result.returncode == 2, result.stderr
        lines = result.stderr.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("error: "), result.stderr
        assert "Traceback" not in result.stderr


def test_cli_validate_ok(recipe_dir):
    path = write_recipe(recipe_dir / "r.yaml", GOOD)
    result = cli("validate", str(path))
    assert result.returncode == 0 and "ok" in result.stdout


@pytest.mark.parametrize("command", ["run", "validate"])
def test_missing_calibration_is_one_line_exit_2(recipe_dir, command):
    (recipe_dir / "seq" / "calib.yaml").unlink()
    path = write_recipe(recipe_dir / "r.yaml", GOOD)
    result = cli_here(command, str(path))
    assert result.returncode == 2 and "Traceback" not in result.stderr
    assert result.stderr.count("\n") == 1 and "camera.settings.path:" in result.stderr
    assert "calib.yaml: calibration file missing" in result.stderr


def test_a_calibration_no_camera_has_fails_validation(recipe_dir):
    calib = recipe_dir / "seq" / "calib.yaml"
    calib.write_text(calib.read_text().replace("baseline_mm:", "baseline_mm: -1 #"))
    result = cli_here("validate", str(write_recipe(recipe_dir / "r.yaml", GOOD)))
    assert result.returncode == 2 and result.stderr.count("\n") == 1
    assert "calib.yaml: baseline_mm must be positive (got -1)" in result.stderr


def test_validate_warns_where_the_working_distance_cannot_resolve_a_limit(recipe_dir):
    far = GOOD.replace("max_disparity: 64", "working_distance_mm: [300, 900]")
    path = write_recipe(recipe_dir / "far.yaml", far)
    result = cli_here("validate", str(path))
    assert result.returncode == 0 and result.stdout.startswith(f"{path}: ok")
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert len(lines) == 1
    # the rule's own line, the distance, the guard band, and what would resolve it
    assert lines[0].startswith(f"{path.resolve()}:13: decision.rules.0: warning: rule 'any deviation_mm > 1': at 900 mm")
    assert re.search(r"resolved at \d+ mm or closer, with a [\d.]+x longer focal length .* or a \d+ mm baseline", lines[0])
    near = write_recipe(recipe_dir / "near.yaml", GOOD.replace("max_disparity: 64", "working_distance_mm: [300, 450]"))
    assert cli_here("validate", str(near)).stderr == ""


def test_validate_warns_of_classes_that_no_rule_covers(recipe_dir):
    # a defect of such a class passes however deep it is
    only = GOOD.replace("{class: any,", "{class: scratches,")
    result = cli_here("validate", str(write_recipe(recipe_dir / "only.yaml", only)))
    assert result.returncode == 0, result.stderr
    assert re.search(r"only\.yaml:11: decision: warning: no rule covers crazing, inclusion, patches, pitted_surface, "
                     r"rolled-in_scale: such a defect passes", result.stderr), result.stderr
    none = GOOD.replace('    - {class: any, quantity: deviation_mm, op: ">", threshold: 1.0}', "    []")
    assert "no rule covers every class the detector reports" in cli_here(
        "validate", str(write_recipe(recipe_dir / "none.yaml", none))).stderr
    rejected = only.replace("decision:", "decision:\n  reject_unruled_defects: true")
    for text, name in ((rejected, "rej.yaml"), (GOOD, "good.yaml")):
        warnings = recipe_warnings(load_recipe(write_recipe(recipe_dir / name, text)))
        assert not [w for w in warnings if "no rule covers" in w], warnings


def test_the_demo_recipe_resolves_its_limits():

    result = cli_here("validate", str(ROOT / "recipes" / "steel_plate.yaml"))
    assert result.returncode == 0 and result.stderr == ""


@pytest.mark.parametrize("setting, message", [
    ("uncertain: pass", r"decision\.uncertain: warning: uncertain: pass lets a part pass whose measurement lies "
                        r"within the guard band"),
    ("coverage_factor: 0.5", r"decision\.coverage_factor: warning: a guard band of 0\.5 u passes a part measured "
                             r"0\.5 u inside a limit, whose true value lies beyond it with a probability of 31%"),
])
def test_validate_warns_of_decisions_that_pass_unproven_parts(recipe_dir, setting, message):
    path = write_recipe(recipe_dir / "loose.yaml", GOOD.replace("decision:\n", f"decision:\n  {setting}\n"))
    result = cli_here("validate", str(path))
    assert result.returncode == 0 and result.stdout.startswith(f"{path}: ok")
    assert re.fullmatch(rf"{re.escape(str(path.resolve()))}:12: {message}.*\n", result.stderr), result.stderr


@pytest.mark.parametrize("proven", ["uncertain: flag", "coverage_factor: 1.0"])
def test_decisions_that_pass_only_proven_parts_are_not_warned_of(recipe_dir, proven):
    path = write_recipe(recipe_dir / "proven.yaml", GOOD.replace("decision:\n", f"decision:\n  {proven}\n"))
    assert not [w for w in recipe_warnings(load_recipe(path)) if "decision." in w]


def test_a_recipe_without_outputs_is_warned_of_by_validate_and_run(recipe_dir):
    # a reject it decides is stored, and no actuator hears of it
    path = write_recipe(recipe_dir / "mute.yaml", GOOD.replace("outputs:\n  - plugin: log\n", "outputs: []\n"))
    warning = f"{path.resolve()}:14: outputs: warning: no output: a rejected part is stored but reaches no actuator"
    result = cli_here("validate", str(path))
    assert result.returncode == 0 and result.stderr.startswith(warning), result.stderr
    run = cli("run", str(path), "--quiet", "--max-frames", "1", "--set", f"results.path={recipe_dir / 'res'}")
    assert run.stderr.startswith(warning), run.stderr
    assert not [w for w in recipe_warnings(load_recipe(write_recipe(recipe_dir / "good.yaml", GOOD))) if "outputs:" in w]


@pytest.mark.parametrize("key, off, what", [
    ("min_mean_grey", 0, "a dark image"),
    ("max_saturated", 1, "a blinded image"),
    ("min_texture", 0, "an image without detail"),
])
def test_validate_warns_of_an_image_check_turned_off(recipe_dir, key, off, what):
    # a frame of nothing then finds no defect: its part passes unseen
    path = write_recipe(recipe_dir / "r.yaml", GOOD)
    result = cli_here("validate", str(path), "--set", f"camera.image_check.{key}={off}")
    assert result.returncode == 0
    assert re.fullmatch(rf"{re.escape(str(path.resolve()))} \(--set camera\.image_check\.{key}\): camera\.image_check\."
                        rf"{key}: warning: off: {what}.*passes instead of being an ERROR\n", result.stderr), result.stderr
    on = load_recipe(path, [f"camera.image_check.{key}=0.5"])
    assert not [w for w in recipe_warnings(on) if "image_check" in w]


@pytest.mark.parametrize("key, value, message", [
    ("confidence", "1.0", r"detector\.confidence: warning: 1 keeps only detections scored 1 or more, which a "
                          r"detector's scores do not reach: nothing is detected and every part passes"),
    ("classes", "[crazing, scratches]", r"detector\.classes: warning: leaves out inclusion, patches, pitted_surface, "
                                        r"rolled-in_scale, which the detector reports: such a defect is not kept, "
                                        r"and its part passes"),
])
def test_validate_warns_of_detector_settings_that_drop_defects_before_any_rule(recipe_dir, key, value, message):
    path = write_recipe(recipe_dir / "r.yaml", GOOD)
    result = cli_here("validate", str(path), "--set", f"detector.{key}={value}")
    assert result.returncode == 0
    assert re.fullmatch(rf"{re.escape(str(path.resolve()))} \(--set detector\.{key}\): {message}.*\n",
                        result.stderr), result.stderr


def test_a_detector_input_under_half_its_training_size_is_warned_of(recipe_dir):
    # the demo's model at 32 px found none of the demo's defects, and every part passed
    path = write_recipe(recipe_dir / "r.yaml", GOOD)
    result = cli_here("validate", str(path), "--set", "detector.settings.imgsz=32")
    assert result.returncode == 0 and result.stderr == (
        f"{path.resolve()} (--set detector.settings.imgsz): detector.settings.imgsz: warning: 32 px of network input, "
        f"under half the 224 px the model was trained at: a defect shrinks below the sizes it learnt, or is cut by the "
        f"tiles, may not be found, and its part then passes\n"), result.stderr
    tiles = recipe_warnings(load_recipe(path, ["detector.settings.imgsz=null", "detector.settings.tile_size=64"]))
    assert [w for w in tiles if "detector.settings.tile_size: warning: 64 px of network input" in w], tiles
    for fine in (["detector.settings.imgsz=112"], ["detector.settings.imgsz=null"],
                 ["detector.settings.imgsz=null", "detector.settings.tile_size=null"]):
        assert not [w for w in recipe_warnings(load_recipe(path, fine)) if "network input" in w], fine


@pytest.mark.parametrize("kept", ["detector.confidence=0.99",
                                  "detector.classes=[crazing, inclusion, patches, pitted_surface, rolled-in_scale, scratches]"])
def test_detector_settings_that_keep_every_defect_are_not_warned_of(recipe_dir, kept):
    loaded = load_recipe(write_recipe(recipe_dir / "r.yaml", GOOD), [kept])
    assert not [w for w in recipe_warnings(loaded) if "detector." in w]


def test_more_threads_per_stage_than_the_machine_has_cores_are_warned_of(recipe_dir, monkeypatch):
    # on the 2-core development machine the demo loop ran at 0.74x its one-thread rate with 8, 0.55x with 32
    monkeypatch.setattr(os, "cpu_count", lambda: 4)
    path = write_recipe(recipe_dir / "r.yaml", GOOD)
    warned = [w for w in recipe_warnings(load_recipe(path, ["threads=5"])) if "threads" in w]
    assert warned == [f"{path.resolve()} (--set threads): threads: warning: 5 threads per stage on this machine's 4 "
                      f"cores: the threads beyond the cores spin against each other and slow the line (auto: half "
                      f"the cores)"]
    for fine in ("threads=4", "threads=auto"):
        assert not [w for w in recipe_warnings(load_recipe(path, [fine])) if "threads" in w], fine


def test_a_deviation_rule_written_the_wrong_way_round_is_warned_of():
    demo = ROOT / "recipes" / "steel_plate.yaml"
    warned = [w for w in recipe_warnings(load_recipe(demo, ["decision.rules.0.op='<'"])) if "decision.rules" in w]
    assert len(warned) == 1 and re.fullmatch(
        r".*steel_plate\.yaml:\d+: decision\.rules\.0: warning: deviation_mm < 1 holds for a defect level with the "
        r"surface: it rejects those and passes every defect deeper than 1 mm \(did you mean > 1\?\)", warned[0])
    assert not [w for w in recipe_warnings(load_recipe(demo)) if "decision.rules" in w]


def test_validate_warns_where_plates_come_closer_than_a_reject_pulse_allows():
    # the demo's 100 ms pulse and the 20 ms low after it need 120 ms: at 12 plates a second (83 ms) a run
    # of rejects falls 37 ms further behind with each one; at 8 (125 ms) it does not
    demo = str(ROOT / "recipes" / "steel_plate.yaml")
    fast = cli_here("validate", demo, "--set", "camera.settings.rate_fps=12")
    assert fast.returncode == 0
    assert re.search(r".*steel_plate\.yaml:\d+: outputs\.0\.settings: warning: a part's pulse and the low after it "
                     r"take 120 ms, longer than the 83 ms between two plates at 12 per second: each reject right "
                     r"after another is 37 ms later than the one before, until beyond max_late_ms it is alarmed "
                     r"instead of sent.*\n", fast.stderr), fast.stderr
    for quiet in (["camera.settings.rate_fps=8"],
                  ["camera.settings.rate_fps=12", "outputs.0.settings.on_reject={write: counter, address: 3}",
                   "outputs.0.settings.max_late_ms=50"]):
        assert recipe_warnings(load_recipe(demo, quiet)) == [], quiet


def test_validate_warns_where_a_late_reject_can_reach_the_next_plate():
    # the demo's 100 ms of lateness against plates 83 ms apart: a reject sent 90 ms late is "delivered" to the
    # plate after its own
    demo = str(ROOT / "recipes" / "steel_plate.yaml")
    warned = [w for w in recipe_warnings(load_recipe(demo, ["camera.settings.rate_fps=12"]))
              if "max_late_ms: warning" in w]
    assert len(warned) == 1 and re.fullmatch(
        r".*steel_plate\.yaml:\d+: outputs\.0\.settings\.max_late_ms: warning: a command up to 100 ms late is still "
        r"sent, but plates come 83 ms apart at 12 per second: a reject that late can reach the next plate instead of "
        r"its own, counted delivered \(give max_late_ms less than 83\)", warned[0]), warned
    assert not [w for w in recipe_warnings(load_recipe(demo)) if "max_late_ms: warning" in w]  # 4 a second: 250 ms


@pytest.mark.parametrize("key, says", [
    ("camera.settings.path", r"camera\.settings\.path: .*x{40}.*: File name too long"),
    ("detector.weights", r"detector\.weights: .*x{40}.*: File name too long"),
    ("results.path", r"results\.path: .*cannot be .*File name too long"),
    ("outputs.0.settings.file", r"outputs\.0\.settings\.file: cannot log to it: .*File name too long"),
])
def test_a_path_the_file_system_refuses_is_a_recipe_error_naming_its_key(recipe_dir, key, says):
    """A name longer than the file system takes raised OSError from the first look at it: a traceback."""
    path = write_recipe(recipe_dir / "r.yaml", GOOD)
    result = cli_here("validate", str(path), "--set", f"{key}={'x' * 300}")
    assert result.returncode == 2 and "Traceback" not in result.stderr
    assert re.fullmatch(rf"error: .*r\.yaml \(--set {re.escape(key)}\): {says}.*\n", result.stderr), result.stderr


@pytest.mark.parametrize("file, says", [
    ("{dir}", r"is a folder"),
    ("r.yaml/rejects.log", r"r\.yaml is a file, not a folder"),
])
def test_a_log_file_that_cannot_be_written_is_said_with_the_recipe_not_at_the_first_reject(recipe_dir, file, says):
    path = write_recipe(recipe_dir / "r.yaml", GOOD)
    with pytest.raises(RecipeError, match=rf"outputs\.0\.settings\.file: cannot log to it: .*{says}"):
        load_recipe(path, [f"outputs.0.settings.file={file.format(dir=recipe_dir)}"])
    load_recipe(path, ["outputs.0.settings.file=logs/new/rejects.log"])  # a folder still to be made is fine
    assert not (recipe_dir / "logs").exists()  # and checking made nothing


def test_a_thread_count_beyond_any_cpu_is_an_error_not_an_overflow(recipe_dir):
    # torch's thread count is a C int: 10^20 ended `inspect stereo` and `eval depth` in a traceback
    path = write_recipe(recipe_dir / "r.yaml", GOOD)
    with pytest.raises(RecipeError, match=r"threads: give auto or a number of threads, 1 to 256 \(got 100000000000"):
        load_recipe(path, ["threads=100000000000000000000"])
    out = cli_here("stereo", str(ROOT / "sim_fixtures/steel_plate/left/000000.jpg"),
                   str(ROOT / "sim_fixtures/steel_plate/right/000000.jpg"), "--max-disp", "64",
                   "--threads", "100000000000000000000")
    assert out.returncode == 2 and "'--threads': 100000000000000000000 is not in the range 1<=x<=256" in out.stderr
    assert "Traceback" not in out.stderr
