"""Finding plugins: everything comes through the ``stereo_inspect`` entry-point group.

The registry never imports a plugin module by name; it asks pluggy to load whatever
packages declare themselves in the entry-point group, built-in ones included.
"""
from __future__ import annotations

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
    def __init__(self, kind: str, name: str, known: list[str]):
        self.kind, self.name, self.known = kind, name, known
        super().__init__(f"unknown {kind} plugin {name!r}; known: {', '.join(known) or 'none'}")


@dataclass
class RegisteredPlugin:
    spec: PluginSpec
    package: str  # the distribution it came from, e.g. "stereo-inspect 0.1.0"


class Registry:
    def __init__(self, manager: pluggy.PluginManager):
        self.manager = manager
        self._plugins: dict[str, dict[str, RegisteredPlugin]] = {kind: {} for kind in PLUGIN_KINDS}
        for kind in PLUGIN_KINDS:
            hook = getattr(manager.hook, _HOOK_BY_KIND[kind])
            for impl in hook.get_hookimpls():
                package = self._package_of(impl.plugin)
                for spec in impl.function() or []:
                    if spec.kind != kind:
                        raise TypeError(f"{impl.plugin_name}: {spec.name!r} is a {spec.kind}, returned as a {kind}")
                    self._plugins[kind].setdefault(spec.name, RegisteredPlugin(spec, package))

    def _package_of(self, plugin: object) -> str:
        for loaded, dist in self.manager.list_plugin_distinfo():
            if loaded is plugin:
                return f"{dist.metadata['name']} {dist.version}"
        return "registered in-process"

    def names(self, kind: PluginKind) -> list[str]:
        return sorted(self._plugins[kind])

    def get(self, kind: PluginKind, name: str) -> RegisteredPlugin:
        try:
            return self._plugins[kind][name]
        except KeyError:
            raise UnknownPlugin(kind, name, self.names(kind)) from None

    def all(self) -> list[RegisteredPlugin]:
        return [p for kind in PLUGIN_KINDS for _, p in sorted(self._plugins[kind].items())]


def make_manager(extra_plugins: tuple[object, ...] = ()) -> pluggy.PluginManager:
    manager = pluggy.PluginManager(hookspecs.PROJECT)
    manager.add_hookspecs(hookspecs)
    manager.load_setuptools_entrypoints(hookspecs.ENTRY_POINT_GROUP)
    for plugin in extra_plugins:
        if not manager.is_registered(plugin):
            manager.register(plugin)
    return manager


@lru_cache(maxsize=1)
def default_registry() -> Registry:
    return Registry(make_manager())
