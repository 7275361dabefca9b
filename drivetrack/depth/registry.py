"""The registry of depth completers: built-ins, ``register_completer`` and entry-point plugins.

A completer factory is any callable ``factory(**params) -> completer``; a completer is a
callable ``completer(sparse) -> dense`` with a ``name`` attribute (see
:class:`drivetrack.depth.completers.DepthCompleter` for the array contract).

Plugins published by other distributions are found through the entry-point group
``drivetrack.depth_completers``: the entry point's name is the completer's name and its object is
the factory, e.g. in a plugin's ``pyproject.toml``::

    [project.entry-points."drivetrack.depth_completers"]
    completionformer = "my_plugin.depth:CompletionFormerCompleter"
"""
from __future__ import annotations

from importlib.metadata import EntryPoint, entry_points
from typing import Any, Callable

__all__ = ["ENTRY_POINT_GROUP", "CompleterPluginError", "UnknownCompleterError",
           "register_completer", "get_completer", "list_completers"]

#: The entry-point group in which plugins publish completer factories.
ENTRY_POINT_GROUP = "drivetrack.depth_completers"

_FACTORIES: dict[str, Callable[..., Any]] = {}


class CompleterPluginError(ImportError):
    """A plugin's entry point could not be loaded or did not give a usable factory."""


class UnknownCompleterError(KeyError):
    """No completer is registered or published under the name (the message lists the known ones)."""

    def __str__(self) -> str:  # KeyError would print the message inside quotes
        return str(self.args[0]) if self.args else ""


def register_completer(name: str, factory: Callable[..., Any], *, replace: bool = False) -> None:
    """Register ``factory`` under ``name`` (it then shadows any plugin of the same name).

    Args:
        name: the name :func:`get_completer` looks up, e.g. ``"nearest"``.
        factory: callable ``factory(**params)`` returning a completer (callable, with ``.name``).
        replace: allow replacing an already registered factory of the same name.
    """
    if not isinstance(name, str) or not name:
        raise ValueError(f"completer name: expected a non-empty string, found {name!r}")
    if not callable(factory):
        raise TypeError(f"completer {name!r}: expected a callable factory, found {factory!r}")
    if name in _FACTORIES and not replace and _FACTORIES[name] is not factory:
        raise ValueError(f"completer {name!r} is already registered ({_FACTORIES[name]!r}); "
                         f"pass replace=True to replace it")
    _FACTORIES[name] = factory


def _plugin_entry_points() -> dict[str, EntryPoint]:
    found: dict[str, EntryPoint] = {}
    for entry_point in entry_points(group=ENTRY_POINT_GROUP):
        found.setdefault(entry_point.name, entry_point)  # first on sys.path wins, like imports
    return found


def list_completers() -> list[str]:
    """Sorted names of every available completer: registered ones and (unloaded) plugins."""
    return sorted(set(_FACTORIES) | set(_plugin_entry_points()))


def _describe(entry_point: EntryPoint) -> str:
    dist = getattr(entry_point, "dist", None)
    where = f" from distribution {dist.name!r}" if dist is not None else ""
    return (f"entry point {entry_point.name!r} = {entry_point.value!r} in group "
            f"{ENTRY_POINT_GROUP!r}{where}")


def _load_plugin(entry_point: EntryPoint) -> Callable[..., Any]:
    try:
        factory = entry_point.load()
    except Exception as error:  # any failure inside a third-party import is the plugin's
        raise CompleterPluginError(
            f"depth completer plugin failed to load: {_describe(entry_point)}: "
            f"{type(error).__name__}: {error}") from error
    if not callable(factory):
        raise CompleterPluginError(f"depth completer plugin is not callable: {_describe(entry_point)} "
                                   f"gave {factory!r}")
    return factory


def get_completer(name: str, **params: Any):
    """Build the completer registered (or published as a plugin) under ``name``.

    Args:
        name: e.g. ``"nearest"``, ``"ipbasic"``, ``"nearest-torch"`` or a plugin's name.
        **params: passed to the factory, e.g. ``max_reach_px=20``.
    Raises:
        UnknownCompleterError (a KeyError): unknown name (the message lists the known ones).
        CompleterPluginError: a plugin's entry point fails to load or builds something unusable.
    """
    factory = _FACTORIES.get(name)
    origin = f"registered factory {factory!r}"
    if factory is None:
        entry_point = _plugin_entry_points().get(name)
        if entry_point is None:
            raise UnknownCompleterError(f"unknown depth completer {name!r}; known: {', '.join(list_completers())}")
        factory = _load_plugin(entry_point)
        origin = _describe(entry_point)
    try:
        completer = factory(**params)
    except CompleterPluginError:
        raise
    except TypeError as error:
        raise TypeError(f"depth completer {name!r} ({origin}) rejected parameters {params}: "
                        f"{error}") from error
    if not callable(completer) or not isinstance(getattr(completer, "name", None), str):
        raise CompleterPluginError(f"depth completer {name!r} ({origin}) built {completer!r}, "
                                   f"expected a callable with a str attribute 'name'")
    return completer
