"""Finding plugins: everything comes through the ``stereo_inspect`` entry-point group.

The registry never imports a plugin module by name; it asks pluggy to load whatever
packages declare themselves in the entry-point group, built-in ones included.
"""
from __future__ import annotations

import difflib
import importlib.metadata
from dataclasses import dataclass
from functools import lru_cache

import pluggy

from core import hookspecs
from core.contracts import PLUGIN_KINDS, PluginKind, PluginSpec

_HOOK_BY_KIND = {
    "camera": "stereo_inspect_cameras",
    "stereo": "stereo_inspect_stereo_backends",
    "detector": "stereo_inspect_detectors",
    "output": "stereo_inspect_outputs",
}


class UnknownPlugin(LookupError):
    def __init__(self, kind: str, name: str, known: list[str], failed: list[str] | None = None):
        self.kind, self.name, self.known = kind, name, known
        why = f"; these plugin packages failed to load: {'; '.join(failed)}" if failed else ""
        close = difflib.get_close_matches(str(name), known, n=1, cutoff=0.6)
        hint = f"; did you mean {close[0]!r}? known" if close else "; known"
        super().__init__(f"unknown {kind} plugin {name!r}{hint}: {', '.join(known) or 'none'}{why}")


class PluginConflict(UnknownPlugin):
    """Two packages register one name: which of them a recipe means cannot be told."""

    def __init__(self, kind: str, name: str, packages: list[str]):
        LookupError.__init__(self, f"{kind} plugin {name!r} is registered by {' and by '.join(packages)}: uninstall "
                                   f"one of them")
        self.kind, self.name, self.known = kind, name, []


@dataclass
class RegisteredPlugin:
    spec: PluginSpec
    package: str  # the distribution it came from, e.g. "stereo-inspect 0.1.0"


class Registry:
    """The plugins of every kind by name. A package that fails to load, or whose hook fails, is left out and
    listed in ``failed`` (one broken third-party package must not stop the others, nor be silent: a recipe
    naming its plugin is told why it is missing); a name two packages register is a ``PluginConflict``."""

    def __init__(self, manager: pluggy.PluginManager):
        self.manager = manager
        self.failed: list[str] = list(getattr(manager, "load_failures", []))
        self._plugins: dict[str, dict[str, RegisteredPlugin]] = {kind: {} for kind in PLUGIN_KINDS}
        self._conflicts: dict[tuple[str, str], list[str]] = {}
        for kind in PLUGIN_KINDS:
            hook = getattr(manager.hook, _HOOK_BY_KIND[kind])
            for impl in hook.get_hookimpls():
                package = self._package_of(impl.plugin)
                try:
                    specs = list(impl.function() or [])
                except Exception as exc:
                    self.failed.append(f"{package} ({impl.plugin_name}): {type(exc).__name__}: {exc}")
                    continue
                for spec in specs:
                    if not isinstance(spec, PluginSpec) or spec.kind != kind:
                        what = f"{spec.name!r}, a {spec.kind}" if isinstance(spec, PluginSpec) else type(spec).__name__
                        self.failed.append(f"{package} ({impl.plugin_name}): {_HOOK_BY_KIND[kind]} returned {what}")
                        continue
                    if spec.name in self._plugins[kind]:
                        first = self._plugins[kind][spec.name].package
                        self._conflicts.setdefault((kind, spec.name), [first]).append(package)
                        continue
                    self._plugins[kind][spec.name] = RegisteredPlugin(spec, package)

    def _package_of(self, plugin: object) -> str:
        for loaded, dist in self.manager.list_plugin_distinfo():
            if loaded is plugin:
                return f"{dist.metadata['name']} {dist.version}"
        return "registered in-process"

    def names(self, kind: PluginKind) -> list[str]:
        """The names of ``kind`` that one package registers (those two register are ``conflicts``)."""
        return sorted(n for n in self._plugins[kind] if (kind, n) not in self._conflicts)

    def get(self, kind: PluginKind, name: str) -> RegisteredPlugin:
        if (kind, name) in self._conflicts:
            raise PluginConflict(kind, name, self._conflicts[(kind, name)])
        try:
            return self._plugins[kind][name]
        except KeyError:
            raise UnknownPlugin(kind, name, self.names(kind), self.failed) from None

    def conflicts(self) -> list[str]:
        """One line per name that several packages register."""
        return [str(PluginConflict(kind, name, packages)) for (kind, name), packages in self._conflicts.items()]

    def all(self) -> list[RegisteredPlugin]:
        return [p for kind in PLUGIN_KINDS for _, p in sorted(self._plugins[kind].items())]


def make_manager(extra_plugins: tuple[object, ...] = ()) -> pluggy.PluginManager:
    """A plugin manager with every package of the entry-point group loaded, one at a time: one that fails to
    import is left out and named in the manager's ``load_failures``."""
    manager = pluggy.PluginManager(hookspecs.PROJECT)
    manager.add_hookspecs(hookspecs)
    manager.load_failures = []
    for entry in importlib.metadata.entry_points(group=hookspecs.ENTRY_POINT_GROUP):
        try:
            manager.load_setuptools_entrypoints(hookspecs.ENTRY_POINT_GROUP, name=entry.name)
        except Exception as exc:
            dist = getattr(entry, "dist", None)
            package = f"{dist.metadata['name']} {dist.version}" if dist is not None else entry.value
            manager.load_failures.append(f"{package} ({entry.name}): {type(exc).__name__}: {exc}")
    for plugin in extra_plugins:
        if not manager.is_registered(plugin):
            manager.register(plugin)
    return manager


@lru_cache(maxsize=1)
def default_registry() -> Registry:
    return Registry(make_manager())
