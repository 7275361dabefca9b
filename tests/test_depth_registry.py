"""Depth completer registry: names, errors, register_completer and entry-point plugins."""
from __future__ import annotations

import sys
import textwrap

import numpy as np
import pytest

from drivetrack.depth import (CompleterPluginError, get_completer, list_completers,
                              register_completer)
from drivetrack.depth import registry

PLUGIN_MODULES = ("dt_depth_plugin_ok", "dt_depth_plugin_broken")


@pytest.fixture
def plugin_dir(tmp_path, monkeypatch):
    """A directory on sys.path holding plugin modules and a .dist-info that declares them, so
    importlib.metadata finds the entry points exactly as for an installed distribution."""
    (tmp_path / "dt_depth_plugin_ok.py").write_text(textwrap.dedent('''
        import numpy as np

        class MeanFill:
            """Fills unknown pixels with the mean of the known returns."""
            name = "meanfill"

            def __init__(self, scale=1.0):
                self.scale = scale

            def __call__(self, sparse):
                known = sparse > 0
                fill = np.float32(sparse[known].mean() * self.scale) if known.any() else 0
                return np.where(known, sparse, fill).astype(np.float32)

        NOT_CALLABLE = 42

        def nameless(**params):
            return lambda sparse: sparse
    '''))
    (tmp_path / "dt_depth_plugin_broken.py").write_text("import no_such_module_for_dt_tests\n")
    dist_info = tmp_path / "dt_depth_plugins-0.1.dist-info"
    dist_info.mkdir()
    (dist_info / "METADATA").write_text("Metadata-Version: 2.1\nName: dt-depth-plugins\nVersion: 0.1\n")
    (dist_info / "entry_points.txt").write_text(textwrap.dedent('''
        [drivetrack.depth_completers]
        meanfill = dt_depth_plugin_ok:MeanFill
        broken = dt_depth_plugin_broken:Factory
        notcallable = dt_depth_plugin_ok:NOT_CALLABLE
        nameless = dt_depth_plugin_ok:nameless
        nearest = dt_depth_plugin_ok:MeanFill

        [some.other.group]
        ignored = dt_depth_plugin_ok:MeanFill
    '''))
    monkeypatch.syspath_prepend(str(tmp_path))
    yield tmp_path
    for name in PLUGIN_MODULES:
        sys.modules.pop(name, None)


def test_builtins_listed():
    names = list_completers()
    assert {"nearest", "ipbasic", "nearest-torch"} <= set(names)
    assert names == sorted(names)


def test_unknown_name_lists_known():
    with pytest.raises(KeyError, match=r"unknown depth completer 'nope'; known: .*ipbasic, nearest") as info:
        get_completer("nope")
    assert str(info.value).startswith("unknown depth completer 'nope'")


def test_bad_parameters_name_the_completer():
    with pytest.raises(TypeError, match=r"depth completer 'nearest'.*rejected parameters \{'radius': 3\}"):
        get_completer("nearest", radius=3)


def test_register_completer_and_duplicates():
    class Halve:
        name = "halve-test"

        def __call__(self, sparse):
            return sparse / 2

    register_completer("halve-test", Halve)
    try:
        assert "halve-test" in list_completers()
        completer = get_completer("halve-test")
        assert completer(np.full((2, 2), 4.0, np.float32))[0, 0] == 2.0
        with pytest.raises(ValueError, match="already registered.*replace=True"):
            register_completer("halve-test", lambda: None)
        with pytest.raises(TypeError, match="expected a callable factory"):
            register_completer("other-test", 3)
        register_completer("broken-test", lambda: object())
        with pytest.raises(CompleterPluginError, match="expected a callable with a str attribute 'name'"):
            get_completer("broken-test")
    finally:
        registry._FACTORIES.pop("halve-test", None)
        registry._FACTORIES.pop("broken-test", None)


def test_plugin_discovered_and_used(plugin_dir):
    names = list_completers()
    assert {"meanfill", "broken", "notcallable"} <= set(names)
    assert "ignored" not in names
    assert "dt_depth_plugin_broken" not in sys.modules  # listing loads nothing
    completer = get_completer("meanfill", scale=2.0)
    sparse = np.zeros((3, 3), np.float32)
    sparse[0, 0], sparse[2, 2] = 2.0, 4.0
    dense = completer(sparse)
    assert completer.name == "meanfill" and dense[1, 1] == pytest.approx(6.0) and dense[0, 0] == 2.0


def test_builtin_shadows_plugin_of_same_name(plugin_dir):
    assert type(get_completer("nearest")).__name__ == "NearestCompleter"


def test_broken_plugins_name_the_entry_point(plugin_dir):
    with pytest.raises(CompleterPluginError,
                       match=r"failed to load: entry point 'broken' = 'dt_depth_plugin_broken:Factory'"
                             r" in group 'drivetrack.depth_completers' from distribution "
                             r"'dt-depth-plugins': ModuleNotFoundError"):
        get_completer("broken")
    with pytest.raises(CompleterPluginError, match=r"not callable: entry point 'notcallable'.*gave 42"):
        get_completer("notcallable")
    with pytest.raises(CompleterPluginError, match=r"'nameless' \(entry point 'nameless'.*str attribute 'name'"):
        get_completer("nameless")
