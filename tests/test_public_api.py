"""The public API a newcomer reads: every package says what it exports, every exported
name is documented, and one public name means one thing across the whole library.

* ``__all__`` of each package lists names the package really binds (explicit imports, no
  lazy ``__getattr__``), without repeats;
* every exported class, function and module has its own docstring (not one inherited from
  a base class, not the one ``NamedTuple``/``dataclass`` generate); exported constants are
  described in their package's docstring;
* clash detector: no name is exported by two packages with different objects, no class
  name is defined twice in the public (non-underscore) modules, and no object is exported
  under two spellings of the same words (``bal_project`` / ``project_bal``).
"""

from __future__ import annotations

import collections
import importlib
import inspect
import pkgutil
import types

import pytest

import jaxpose

PACKAGES = [
    "jaxpose", "jaxpose.lie", "jaxpose.optim", "jaxpose.graph", "jaxpose.dynamics",
    "jaxpose.filters", "jaxpose.control", "jaxpose.geometry", "jaxpose.imu", "jaxpose.io",
    "jaxpose.smoothing",
]
# modules whose import needs an optional dependency (MuJoCo, matplotlib)
OPTIONAL = {"jaxpose.dynamics.mjx", "jaxpose.plot"}
# deliberate short aliases inside one package (PyPose's names): same object, two names
ALIASES = {("GN", "GaussNewton"), ("LM", "LevenbergMarquardt")}


def _exports(pkg_name: str) -> list[tuple[str, object]]:
    pkg = importlib.import_module(pkg_name)
    return [(name, getattr(pkg, name)) for name in pkg.__all__]


def _all_modules() -> list[types.ModuleType]:
    """Every module of the package, private ones included (implementation modules are
    private; the classes they define are what the packages export)."""
    mods = [jaxpose]
    for info in pkgutil.walk_packages(jaxpose.__path__, "jaxpose."):
        try:
            mods.append(importlib.import_module(info.name))
        except ImportError:
            if info.name not in OPTIONAL:
                raise
    return mods


def _own_doc(obj: object) -> str:
    """The docstring written for ``obj`` itself ('' when missing or generated)."""
    if inspect.isclass(obj):
        doc = vars(obj).get("__doc__") or ""
        # NamedTuple and dataclass invent "Name(field, ...)" when none is written
        return "" if doc.startswith(f"{obj.__name__}(") else doc.strip()
    return (inspect.getdoc(obj) or "").strip()


@pytest.mark.parametrize("pkg_name", PACKAGES)
def test_all_lists_names_the_package_binds(pkg_name):
    pkg = importlib.import_module(pkg_name)
    names = pkg.__all__
    assert len(names) == len(set(names)), f"{pkg_name}.__all__ repeats a name"
    missing = [n for n in names if n not in vars(pkg)]
    assert not missing, f"{pkg_name}.__all__ names {missing}, which the package does not import"


@pytest.mark.parametrize("pkg_name", PACKAGES)
def test_exported_names_are_documented(pkg_name):
    pkg = importlib.import_module(pkg_name)
    undocumented = []
    for name, obj in _exports(pkg_name):
        if name.startswith("__"):
            continue
        if inspect.ismodule(obj) or inspect.isclass(obj) or callable(obj):
            if not _own_doc(obj):
                undocumented.append(name)
        elif name not in (pkg.__doc__ or ""):
            undocumented.append(f"{name} (a constant not described in the package docstring)")
    assert not undocumented, f"{pkg_name}: undocumented exports {undocumented}"


def test_no_name_exported_with_two_meanings():
    where = collections.defaultdict(dict)  # name -> {id(obj): [packages]}
    for pkg_name in PACKAGES:
        for name, obj in _exports(pkg_name):
            where[name].setdefault(id(obj), []).append(pkg_name)
    clashes = {name: list(objs.values()) for name, objs in where.items() if len(objs) > 1}
    assert not clashes, f"names exported with different meanings: {clashes}"


def test_no_public_class_name_defined_twice():
    defined = collections.defaultdict(list)
    for mod in _all_modules():
        for name, obj in vars(mod).items():
            if (not name.startswith("_") and inspect.isclass(obj)
                    and obj.__module__ == mod.__name__):
                defined[name].append(mod.__name__)
    clashes = {name: mods for name, mods in defined.items() if len(mods) > 1}
    assert not clashes, f"classes of the same name in public modules: {clashes}"


def test_one_function_one_name():
    names_of = collections.defaultdict(set)  # id(obj) -> exported names
    spellings = collections.defaultdict(set)  # sorted words -> exported names
    for pkg_name in PACKAGES:
        for name, obj in _exports(pkg_name):
            if inspect.isfunction(obj) or inspect.isclass(obj):
                names_of[id(obj)].add(name)
            words = name.split("_")
            if len(words) > 1:
                spellings[tuple(sorted(words))].add(name)
    two_names = [sorted(n) for n in names_of.values()
                 if len(n) > 1 and tuple(sorted(n)) not in ALIASES]
    assert not two_names, f"one object exported under several names: {two_names}"
    def inverse_pair(names: set[str]) -> bool:  # a_to_b / b_to_a: a conversion and its inverse
        a, b = sorted(names)
        return len(names) == 2 and "_to_" in a and a.split("_to_")[::-1] == b.split("_to_")

    reordered = [sorted(n) for n in spellings.values() if len(n) > 1 and not inverse_pair(n)]
    assert not reordered, f"the same words exported in two orders: {reordered}"


def test_ready_made_problems_are_reached_the_same_way():
    g = jaxpose.graph
    for name in ("optimize_pose_graph", "pose_graph_problem", "optimize_bal",
                 "bundle_adjustment_problem", "chordal_initialization", "gnc", "marginals"):
        assert name in g.__all__, f"jaxpose.graph does not export {name}"


# modules that are public namespaces on purpose (everything else is a private ``_name.py``
# whose public names its package re-exports)
NAMESPACES = {
    "jaxpose.cli", "jaxpose.datasets", "jaxpose.interop", "jaxpose.plot", "jaxpose.results",
    "jaxpose.sharding", "jaxpose.testing", "jaxpose.lie.convert", "jaxpose.lie.manifold",
    "jaxpose.lie.series", "jaxpose.dynamics.mjx", "jaxpose.smoothing.examples",
}


def test_implementation_modules_are_private():
    public = {info.name for info in pkgutil.walk_packages(jaxpose.__path__, "jaxpose.")
              if not info.ispkg and not any(p.startswith("_") for p in info.name.split("."))}
    assert public == NAMESPACES, (
        f"public modules that are not namespaces: {sorted(public - NAMESPACES)}; "
        f"name them _module.py and re-export their public names from the package"
    )
    # and no package binds a private module under a public name
    for pkg_name in PACKAGES:
        pkg = importlib.import_module(pkg_name)
        for name, obj in vars(pkg).items():
            if isinstance(obj, types.ModuleType) and not name.startswith("_"):
                assert obj.__name__ in NAMESPACES | set(PACKAGES), (
                    f"{pkg_name}.{name} is the private module {obj.__name__}"
                )


def test_detector_sees_a_clash(monkeypatch):
    """The clash detector is live: a second ``LinearizedSystem`` in optim is reported."""
    import jaxpose.optim as optim

    monkeypatch.setattr(optim, "LinearizedSystem",
                        type("LinearizedSystem", (), {"__doc__": "impostor"}), raising=False)
    monkeypatch.setattr(optim, "__all__", [*optim.__all__, "LinearizedSystem"])
    with pytest.raises(AssertionError, match="LinearizedSystem"):
        test_no_name_exported_with_two_meanings()
