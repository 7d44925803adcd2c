"""Loading a recipe: safe YAML, ``--set`` overrides, schema and plugin-settings validation.

Every problem becomes one ``RecipeError`` whose message names the file, the line and the
key path (``recipes/x.yaml:12: stereo.max_disparity: ...``), which the CLI prints as one line.
"""
from __future__ import annotations

import copy
import difflib
import hashlib
import json
import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Union, get_args, get_origin

import yaml
from pydantic import BaseModel, ValidationError

from core.recipe.schema import Recipe
from core.registry import Registry, UnknownPlugin, default_registry
from drivers import text_files, yaml_reader
from drivers.sequence_folder import labelled_sequence_problem, list_frames
from drivers.stereo_geometry import calibration_problem


class RecipeError(Exception):
    """A recipe that cannot be used; ``str()`` is the one-line message for the user."""

    def __init__(self, message: str):
        # a value that holds a line break (a path, a plugin's own message) is written as its escape: one line
        super().__init__(message.replace("\r", "\\r").replace("\n", "\\n"))


KeyPath = tuple[str | int, ...]


def _dotted(path: KeyPath) -> str:
    return ".".join(str(p) for p in path) or "(top level)"


@dataclass
class LoadedRecipe:
    recipe: Recipe
    path: Path
    text_hash: str
    plugin_settings: dict[str, Any] = field(default_factory=dict)  # "camera", "stereo", "detector", "outputs.N"
    lines: dict[KeyPath, int] = field(default_factory=dict)  # 1-based line of every key of the file
    overridden: dict[KeyPath, str] = field(default_factory=dict)  # keys given on the command line, and how
    # the classes the detector states from its settings, None where it states them only once built
    detector_classes: list[str] | None = None

    def where(self, key: KeyPath) -> str:
        """``file:line`` of the key, or of the nearest key above it that the file has (or its --set)."""
        return _Locator(self.path, self.lines, self.overridden).where(key)

    def describe(self, key: KeyPath, message: str) -> str:
        """``file:line: dotted.key: message``, as a recipe error reads."""
        return _Locator(self.path, self.lines, self.overridden).describe(key, message)

    @property
    def directory(self) -> Path:
        return self.path.parent

    def resolve(self, relative: str) -> Path:
        p = Path(relative).expanduser()
        return p if p.is_absolute() else (self.directory / p).resolve()


class _Locator:
    def __init__(self, path: Path, lines: dict[KeyPath, int], overridden: dict[KeyPath, str]):
        self.path, self.lines, self.overridden = path, lines, overridden

    def where(self, key: KeyPath) -> str:
        # a key under one given on the command line has the command line's value, whatever line the file had
        for n in range(len(key), 0, -1):
            if tuple(key[:n]) in self.overridden:
                return f"{self.path} ({self.overridden[tuple(key[:n])]})"
        for n in range(len(key), 0, -1):
            if tuple(key[:n]) in self.lines:
                return f"{self.path}:{self.lines[tuple(key[:n])]}"
        return str(self.path)

    def describe(self, key: KeyPath, message: str) -> str:
        return f"{self.where(key)}: {_dotted(key)}: {message}"

    def error(self, key: KeyPath, message: str) -> RecipeError:
        return RecipeError(self.describe(key, message))


def first_problem(exc: ValidationError, model: type[BaseModel]) -> tuple[KeyPath, str]:
    """Where in ``model`` the first error of ``exc`` lies and what it is, in words: an unknown key with the
    closest known one, a required key missing, a section given as a scalar with the keys it takes, or the
    value's problem with the value."""
    err = exc.errors()[0]
    loc = tuple(p for p in err["loc"] if p != "__root__")
    kind = err["type"]
    keys = keys_at(model, loc) if kind == "model_type" else []
    if kind == "extra_forbidden":
        close = difflib.get_close_matches(str(loc[-1]), keys_at(model, loc[:-1]), n=1, cutoff=0.6)
        message = "unknown key" + (f"; did you mean {close[0]!r}?" if close else "")
    elif kind == "missing":
        message = "required key missing"
    elif keys:
        message = f"should be a mapping of {', '.join(keys)} (got {err.get('input')!r})"
    else:
        message = err["msg"].removeprefix("Value error, ")
        if "input" in err and kind not in ("model_type", "dict_type") and not isinstance(err["input"], dict) \
                and not _names(message, err["input"]):
            message += f" (got {err['input']!r})"
    return loc, message


def _names(message: str, value: Any) -> bool:
    """Whether ``message`` already gives ``value``: a file it read, by its path, or the value as written, standing
    alone (``'surfac'`` is not named by ``'surface'``, nor ``0`` by ``0.05``)."""
    if isinstance(value, str) and ("/" in value or "\\" in value) and value.rstrip("/") in message:
        return True
    return re.search(rf"(?<![\w.']){re.escape(repr(value))}(?![\w.'])", message) is not None


def _first_error(exc: ValidationError, base: KeyPath, locator: _Locator, model: type[BaseModel]) -> RecipeError:
    loc, message = first_problem(exc, model)
    more = len(exc.errors()) - 1
    if more:
        message += f" (and {more} more problem{'s' if more > 1 else ''})"
    return locator.error(base + loc, message)


def keys_at(model: type[BaseModel], path: KeyPath) -> list[str]:
    """The keys the section of ``model`` at ``path`` (names and list indices) accepts; [] where the path
    does not lead to a section."""
    annotation: Any = model
    for part in path:
        annotation = next((a for a in (_step(c, part) for c in _members(annotation)) if a is not None), None)
        if annotation is None:
            return []
    section = next((c for c in _members(annotation) if isinstance(c, type) and issubclass(c, BaseModel)), None)
    return [] if section is None else [f.alias or name for name, f in section.model_fields.items()]


def _members(annotation: Any) -> list[Any]:
    """An annotation's alternatives (``A | B | None`` -> A, B), else itself."""
    return [a for a in get_args(annotation) if a is not type(None)] if get_origin(annotation) in (Union, type(int | None)) \
        else [annotation]


def _step(annotation: Any, part: str | int) -> Any:
    """The annotation of ``part`` inside ``annotation`` (a model's field, a list's item), or None."""
    if isinstance(part, int) and get_origin(annotation) in (list, tuple):
        return get_args(annotation)[0]
    if isinstance(part, str) and isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return next((f.annotation for name, f in annotation.model_fields.items() if (f.alias or name) == part), None)
    return None


# the sections whose settings belong to the plugin they name
PLUGIN_KEYS = {"camera": "plugin", "stereo": "backend", "detector": "plugin"}


def _without_settings_of_replaced_plugins(data: dict, overrides: list[str] | tuple[str, ...]) -> dict:
    """A copy of ``data`` without the settings of a plugin that ``--set`` replaces: ``--set
    stereo.backend=opencv_sgbm`` on a recipe written for torch_sgm starts the other backend from its own
    defaults and the settings ``--set`` gives it, not from torch_sgm's. Likewise a camera's or a detector's."""
    replaced = copy.deepcopy(data)
    for assignment in overrides:
        apply_override(replaced, assignment)
    data = copy.deepcopy(data)
    for section, key in PLUGIN_KEYS.items():
        before, after = data.get(section), replaced.get(section)
        if isinstance(before, dict) and isinstance(after, dict) and before.get(key) != after.get(key):
            before.pop("settings", None)
    return data


def apply_override(data: dict, assignment: str) -> KeyPath:
    """Apply ``a.b.c=value`` (value parsed as YAML, list items by index) to ``data``."""
    if "=" not in assignment:
        raise RecipeError(f"--set {assignment}: expected key.path=value")
    dotted, raw = assignment.split("=", 1)
    parts: list[str | int] = [int(p) if p.isdigit() else p for p in dotted.strip().split(".")]
    if not all(str(p) for p in parts):
        raise RecipeError(f"--set {assignment}: empty key in {dotted!r}")
    try:
        value = yaml_reader.option_value(raw)
    except yaml_reader.Misread as exc:
        raise RecipeError(f"--set {assignment}: {exc.described}") from None
    node: Any = data
    for i, part in enumerate(parts[:-1]):
        if isinstance(node, list):
            if not isinstance(part, int) or part >= len(node):
                raise RecipeError(f"--set {assignment}: {_dotted(tuple(parts[: i + 1]))}: no such list item")
            node = node[part]
        elif isinstance(node, dict):
            node = node.setdefault(part, {})
        else:
            raise RecipeError(f"--set {assignment}: {_dotted(tuple(parts[:i]))} is not a mapping")
    last = parts[-1]
    if isinstance(node, list):
        if not isinstance(last, int) or last >= len(node):
            raise RecipeError(f"--set {assignment}: {dotted}: no such list item")
        node[last] = value
    elif isinstance(node, dict):
        node[last] = value
    else:
        raise RecipeError(f"--set {assignment}: {_dotted(tuple(parts[:-1]))} is not a mapping")
    return tuple(parts)


def _validate_plugin(
    registry: Registry, kind: str, name: str, settings: dict, key: KeyPath, locator: _Locator, context: dict
) -> dict:
    try:
        plugin = registry.get(kind, name)
    except UnknownPlugin as exc:
        raise locator.error(key + ("plugin" if kind != "stereo" else "backend",), str(exc)) from None
    model: type[BaseModel] | None = plugin.spec.settings_model
    if model is None:
        return dict(settings)
    try:
        validated = model.model_validate(settings, context=context).model_dump()
    except ValidationError as exc:
        raise _first_error(exc, key + ("settings",), locator, model) from None
    except OSError as exc:  # a validator that looked at a path the system refuses (a name too long, no permission)
        named = [k for k, v in settings.items() if isinstance(v, str) and v and v in str(exc.filename)]
        raise locator.error(key + ("settings",) + tuple(named[:1]), f"{exc.filename or ''}: {exc.strerror or exc}") from None
    # a third-party model on pydantic's own BaseModel reads the text "nan" as a number
    _check_finite(validated, key + ("settings",), locator)
    return validated


def load_recipe(path: str | Path, overrides: list[str] | tuple[str, ...] = (), registry: Registry | None = None,
                options: dict[str, str] | None = None) -> LoadedRecipe:
    """The recipe at ``path`` with ``overrides`` (``key.path=value``, as ``--set`` gives them) applied, checked
    against the schema and its plugins' settings. ``options`` names the command-line option that gave an
    override's key (``{"threads": "--threads"}``), for errors and warnings to point at; ``--set`` otherwise."""
    path = Path(path)
    try:
        text = text_files.decode(path.read_bytes())
    except FileNotFoundError:
        raise RecipeError(f"{path}: recipe file not found") from None
    except text_files.NotUtf8 as exc:
        raise RecipeError(f"{path}:{exc.line}: {exc}: save the recipe as UTF-8") from None
    except OSError as exc:
        raise RecipeError(f"{path}: cannot read recipe ({exc.strerror})") from None
    try:
        data, lines = yaml_reader.safe_load_lines(text)
    except yaml_reader.Misread as exc:
        raise RecipeError(f"{path}:{exc.line}: {exc.described}") from None
    except yaml_reader.StructureError as exc:
        raise RecipeError(f"{path}:{exc.line}: {exc.problem}") from None
    except yaml.MarkedYAMLError as exc:
        mark = exc.problem_mark
        where = f"{path}:{mark.line + 1}" if mark else str(path)
        raise RecipeError(f"{where}: YAML syntax error: {exc.problem or exc}") from None
    except yaml.YAMLError as exc:
        raise RecipeError(f"{path}: YAML error: {str(exc).splitlines()[0]}") from None
    if not isinstance(data, dict):
        raise RecipeError(f"{path}: a recipe must be a mapping of sections (camera, stereo, ...)")

    data = _without_settings_of_replaced_plugins(data, overrides)
    overridden = {}
    for assignment in overrides:
        key = apply_override(data, assignment)
        overridden[key] = (options or {}).get(_dotted(key), f"--set {_dotted(key)}")
    locator = _Locator(path, lines, overridden)
    _check_finite(data, (), locator)
    try:
        recipe = Recipe.model_validate(data)
    except ValidationError as exc:
        raise _first_error(exc, (), locator, Recipe) from None

    loaded = LoadedRecipe(
        recipe=recipe,
        path=path.resolve(),
        text_hash=hashlib.sha256(json.dumps(data, sort_keys=True, default=str).encode()).hexdigest()[:16],
        lines=lines,
        overridden=overridden,
    )
    registry = registry or default_registry()
    context = {"recipe_dir": loaded.directory}

    if recipe.detector.weights is not None:
        weights = loaded.resolve(recipe.detector.weights)
        try:
            found = weights.is_file()
        except OSError as exc:  # a name too long for the file system, a folder that cannot be looked into
            raise locator.error(("detector", "weights"), f"{weights}: {exc.strerror or exc}") from None
        if not found:
            raise locator.error(("detector", "weights"), f"weights file not found: {weights}")
    _check_verify_path(loaded, locator)
    loaded.plugin_settings["camera"] = _validate_plugin(
        registry, "camera", recipe.camera.plugin, recipe.camera.settings, ("camera",), locator, context
    )
    loaded.plugin_settings["stereo"] = _validate_plugin(
        registry, "stereo", recipe.stereo.backend, recipe.stereo.settings, ("stereo",), locator, context
    )
    loaded.plugin_settings["detector"] = _validate_plugin(
        registry, "detector", recipe.detector.plugin, recipe.detector.settings, ("detector",), locator, context
    )
    for index, output in enumerate(recipe.outputs):
        loaded.plugin_settings[f"outputs.{index}"] = _validate_plugin(
            registry, "output", output.plugin, output.settings, ("outputs", index), locator, context
        )
    _check_weights_pin(loaded, locator)
    _check_classes(loaded, registry, locator)
    _check_output_delays(loaded, registry, locator)
    _check_camera_geometry(loaded, registry, locator)
    return loaded


def _check_verify_path(loaded: LoadedRecipe, locator: _Locator) -> None:
    """The master parts' folder (``verify.path``) readable to its end, each frame labelled: a frame it could not
    read at the start would leave the check half done."""
    if loaded.recipe.verify.path is None:
        return
    folder = loaded.resolve(loaded.recipe.verify.path)
    try:
        found = folder.is_dir()
    except OSError as exc:
        raise locator.error(("verify", "path"), f"{folder}: {exc.strerror or exc}") from None
    if not found:
        raise locator.error(("verify", "path"), f"sequence folder not found: {folder}")
    problem = labelled_sequence_problem(folder)
    if problem is not None:
        raise locator.error(("verify", "path"), problem)
    # a master part whose images are missing would not be inspected, and the check would vouch for it all the same
    frames = {f.frame_id for f in list_frames(folder)}
    orphans = sorted(p.name for p in (folder / "labels").glob("*.json") if p.stem not in frames)
    if orphans:
        more = f" (and {len(orphans) - 1} more labels)" if len(orphans) > 1 else ""
        raise locator.error(("verify", "path"), f"{folder / 'labels' / orphans[0]}: no left/ or right/ image of that "
                                               f"frame{more}")


def _check_finite(node: Any, key: KeyPath, locator: _Locator) -> None:
    """No NaN or infinity anywhere, a plugin's settings included: every comparison with NaN is false, so a
    rule whose threshold is ``.nan`` would never reject."""
    if isinstance(node, float) and not math.isfinite(node):
        raise locator.error(key, f"must be a finite number (got {node})")
    items = node.items() if isinstance(node, dict) else enumerate(node) if isinstance(node, (list, tuple)) else ()
    for k, value in items:
        _check_finite(value, key + (k,), locator)


def _check_camera_geometry(loaded: LoadedRecipe, registry: Registry, locator: _Locator) -> None:
    """Where the camera plugin states its geometry from its settings: it must be one a camera can have
    (``drivers.stereo_geometry``; else every deviation could read about 0 mm), and the stereo search range
    must fit its image (else every part would be an ERROR). A camera that cannot state it is not checked
    here (``inspect validate`` says so)."""
    calib = camera_answer(loaded, registry, "calibration")
    if calib is None:
        return
    problem = calibration_problem(calib.focal_px, calib.baseline_mm, calib.cx, calib.cy, calib.width, calib.height,
                                  calib.doffs)
    if problem is not None:
        raise locator.error(("camera",), f"the camera's calibration is no camera's: {problem}")
    stereo = loaded.recipe.stereo
    try:
        stereo.search_range(calib)
    except ValueError:
        fb = calib.focal_px * calib.baseline_mm
        if stereo.working_distance_mm is not None:
            nearest = fb / (calib.width - 1 - stereo.RANGE_MARGIN_PX + calib.doffs)
            raise locator.error(("stereo", "working_distance_mm"), (
                f"the camera cannot see {stereo.working_distance_mm[0]:g} mm with both eyes: at its geometry "
                f"(f {calib.focal_px:.4g} px, baseline {calib.baseline_mm:.4g} mm) that is "
                f"{calib.disparity_px(stereo.working_distance_mm[0]):.4g} px of disparity in a {calib.width} px wide "
                f"image; the nearest it can match is {math.ceil(nearest)} mm")) from None
        raise locator.error(("stereo", "max_disparity"), f"{stereo.max_disparity:g} px of disparity does not fit the "
                            f"camera's {calib.width} px wide image") from None


def file_sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def _check_weights_pin(loaded: LoadedRecipe, locator: _Locator) -> None:
    detector = loaded.recipe.detector
    if detector.sha256 is None:
        return
    if detector.weights is None:
        raise locator.error(("detector", "sha256"), "pins a weights file: give detector.weights too")
    actual = file_sha256(loaded.resolve(detector.weights))
    if actual != detector.sha256.lower():
        raise locator.error(("detector", "sha256"), f"{loaded.resolve(detector.weights)} has SHA-256 {actual}, "
                            f"not the pinned {detector.sha256.lower()}")


def detector_settings(loaded: LoadedRecipe) -> dict:
    """The detector plugin's settings as the engine hands them over (confidence and weights from the recipe)."""
    settings = dict(loaded.plugin_settings["detector"])
    settings["confidence"] = loaded.recipe.detector.confidence
    if loaded.recipe.detector.weights is not None:
        settings["weights"] = str(loaded.resolve(loaded.recipe.detector.weights))
    return settings


def _check_classes(loaded: LoadedRecipe, registry: Registry, locator: _Locator) -> None:
    """Every class a rule or ``detector.classes`` names must be one the detector reports: a misspelled one
    would never apply and every part with that defect would pass."""
    recipe = loaded.recipe
    try:
        known = detector_classes(loaded, registry)
    except Exception as exc:  # the detector's own reason (weights refused, unreadable, ...)
        key = ("detector", "weights") if recipe.detector.weights is not None else ("detector", "plugin")
        raise locator.error(key, str(exc)) from None
    loaded.detector_classes = known
    if known is None:  # checked against the detector itself when the run starts
        return
    for key, name in named_classes(recipe):
        if name not in known:
            raise locator.error(key, unknown_class_message(name, known))


def detector_classes(loaded: LoadedRecipe, registry: Registry) -> list[str] | None:
    """The classes the recipe's detector reports, from its settings, or None where its plugin states them
    only once built; the plugin's exception where it cannot say (its weights unreadable, say)."""
    from core.contracts import PluginContext

    spec = registry.get("detector", loaded.recipe.detector.plugin).spec
    if spec.class_names is None:
        return None
    return list(spec.class_names(detector_settings(loaded), PluginContext(recipe_dir=loaded.directory)))


def named_classes(recipe) -> list[tuple[KeyPath, str]]:
    """(key, class) of every class the recipe names: its rules' (but ``any``) and ``detector.classes``."""
    named = [(("decision", "rules", i, "class"), r.class_) for i, r in enumerate(recipe.decision.rules) if r.class_ != "any"]
    return named + [(("detector", "classes", i), c) for i, c in enumerate(recipe.detector.classes or [])]


def unknown_class_message(name: str, known: list[str]) -> str:
    close = difflib.get_close_matches(name, known, n=1, cutoff=0.6)
    hint = f"; did you mean {close[0]!r}?" if close else ""
    return f"unknown class {name!r}{hint} The detector knows: {', '.join(known)} (or any)"


def output_answers(loaded: LoadedRecipe, registry: Registry, question: str) -> list[tuple[int, Any]]:
    """(index, answer) of every output whose plugin answers one of ``PluginSpec``'s optional questions
    (``actuator_delay``, ``part_interval``) from its settings alone, where the answer is not None."""
    from core.contracts import PluginContext

    ctx = PluginContext(recipe_dir=loaded.directory)
    answers = []
    for index, output in enumerate(loaded.recipe.outputs):
        ask = getattr(registry.get("output", output.plugin).spec, question)
        if ask is not None:
            answer = ask(loaded.plugin_settings[f"outputs.{index}"], ctx)
            if answer is not None:
                answers.append((index, answer))
    return answers


def output_delays_s(loaded: LoadedRecipe, registry: Registry) -> list[tuple[int, float]]:
    """(index, seconds from a part's capture to its command) of every output that states it
    (``PluginSpec.actuator_delay``)."""
    return output_answers(loaded, registry, "actuator_delay")


def camera_answer(loaded: LoadedRecipe, registry: Registry, question: str) -> Any:
    """The camera plugin's answer to one of ``PluginSpec``'s optional questions (``calibration``,
    ``frame_rate``) from its settings alone; None where it has no answer or cannot give one."""
    spec = registry.get("camera", loaded.recipe.camera.plugin).spec
    return spec.answer(question, loaded.plugin_settings["camera"], loaded.directory)


def _check_output_delays(loaded: LoadedRecipe, registry: Registry, locator: _Locator) -> None:
    """A timed output's delay must leave the inspection one frame period at least: a part is decided up to a
    frame period after its capture, so a shorter delay makes every command late."""
    fps = camera_answer(loaded, registry, "frame_rate")
    if not fps:
        return
    period = 1.0 / fps
    for index, delay in output_delays_s(loaded, registry):
        if delay < period:
            settings = loaded.plugin_settings[f"outputs.{index}"]
            key = next((("outputs", index, "settings", k) for k in ("delay_ms", "actuator_distance_mm")
                        if settings.get(k) is not None), ("outputs", index, "settings"))
            raise locator.error(key,
                                f"the command is due {1000 * delay:.0f} ms after a part's capture, less than the camera's "
                                f"frame period ({1000 * period:.0f} ms at {fps:g} fps) in which the part is decided: "
                                f"set delay_ms to at least {1000 * period:.0f} (or the actuator further downstream)")
