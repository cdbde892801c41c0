"""The import graph follows the pipeline: no arrow runs from an earlier floor to a later one.

Every ``import`` and ``from … import`` of every module (module level and inside functions, read from
the source with ``ast``; ``capture/`` is ``mifacerf.capture``, ``plugins/`` is ``mifacerf.plugins``)
is an arrow from the importing module to the imported one. The floors, bottom to top
(``docs/architecture.md``):

====  ===========================================================================================
0     ground floor: the root modules of ``mifacerf/`` (camera, environment, imageio, rig, variant,
      jitarrays, methods, stats, …), :mod:`mifacerf.geometry`, :mod:`mifacerf.formats`
1     capture, synthetic
2     registration
3     blending
4     rendering, plugins
5     tracking
6     evaluation, studio
7     the facade: the package root (``mifacerf/__init__.py``), ``demo.py``, ``cli.py``
====  ===========================================================================================

An arrow may point down or sideways, never up; the stage packages have no cycle (sideways arrows
included); no module uses an underscore-private name of another package. Imports by name
(``importlib.import_module("…")``: the CLI's command table, the root's lazy attributes,
``variant.ensure_plugins``) are not arrows of this graph.
"""
from __future__ import annotations

import ast
from collections import defaultdict

import pytest

from helpers.source_tree import ROOT, source_modules, source_packages

FLOORS = {
    "capture": 1, "synthetic": 1,
    "registration": 2,
    "blending": 3,
    "rendering": 4, "plugins": 4,
    "tracking": 5,
    "evaluation": 6, "studio": 6,
}
GROUND_PACKAGES = ("geometry", "formats")
FACADE = ("demo", "cli")
FLOOR_NAMES = ["ground floor", "capture/synthetic", "registration", "blending", "rendering/plugins",
               "tracking", "evaluation/studio", "facade (root, demo, cli)"]

MODULES = source_modules()
PACKAGES = set(source_packages())


def unit(module: str) -> str:
    """The package a module belongs to for these rules: ``mifacerf.<x>`` (``mifacerf`` for the root)."""
    parts = module.split(".")
    return ".".join(parts[:2])


def floor(module: str) -> int:
    parts = module.split(".")
    if len(parts) == 1 or parts[1] in FACADE:
        return 7
    if parts[1] in FLOORS:
        return FLOORS[parts[1]]
    return 0  # root modules, geometry, formats


def is_stage(module: str) -> bool:
    return 0 < floor(module) < 7


def _resolve(module: str, node: ast.ImportFrom) -> str:
    if not node.level:
        return node.module or ""
    base = module.split(".") if module in PACKAGES else module.split(".")[:-1]
    base = base[: len(base) - node.level + 1]
    return ".".join(base + ([node.module] if node.module else []))


def _known(name: str) -> str | None:
    """The longest prefix of ``name`` that is a module of the tree."""
    parts = name.split(".")
    for k in range(len(parts), 0, -1):
        if ".".join(parts[:k]) in MODULES:
            return ".".join(parts[:k])
    return None


class Arrow:
    def __init__(self, source: str, target: str, line: int, private: str | None = None):
        self.source, self.target, self.line, self.private = source, target, line, private

    def __str__(self) -> str:
        path = MODULES.get(self.source)
        where = f"{path.relative_to(ROOT) if path else self.source}:{self.line}"
        what = f"{self.target}.{self.private}" if self.private else self.target
        return f"{where}  {self.source} -> {what}"


def arrows_of(module: str, text: str | None = None) -> tuple[list[Arrow], list[Arrow]]:
    """(arrows to modules of the tree, uses of their underscore-private names) of one module.

    ``text``: the module's source (default: its file).
    """
    tree = ast.parse(MODULES[module].read_text() if text is None else text, module)
    arrows, private = [], []
    aliases: dict[str, str] = {}  # local name -> module of the tree it is bound to
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for a in node.names:
                target = _known(a.name)
                if target:
                    arrows.append(Arrow(module, target, node.lineno))
                    hidden = [p for p in target.split(".") if _private(p)]
                    if hidden:
                        private.append(Arrow(module, target.rsplit(".", 1)[0], node.lineno, target.split(".")[-1]))
                    if a.asname and target == a.name:
                        aliases[a.asname] = target
        elif isinstance(node, ast.ImportFrom):
            base = _resolve(module, node)
            for a in node.names:
                sub = f"{base}.{a.name}"
                if sub in MODULES:
                    arrows.append(Arrow(module, sub, node.lineno))
                    aliases[a.asname or a.name] = sub
                    if _private(a.name):
                        private.append(Arrow(module, base, node.lineno, a.name))
                elif _known(base):
                    arrows.append(Arrow(module, _known(base), node.lineno))
                    if _private(a.name):
                        private.append(Arrow(module, _known(base), node.lineno, a.name))
    for node in ast.walk(tree):
        if (isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) and node.value.id in aliases
                and _private(node.attr)):
            private.append(Arrow(module, aliases[node.value.id], node.lineno, node.attr))
    return arrows, private


def _private(name: str) -> bool:
    return name.startswith("_") and not (name.startswith("__") and name.endswith("__"))


def _all():
    arrows, private = [], []
    for m in MODULES:
        a, p = arrows_of(m)
        arrows += a
        private += p
    return arrows, private


ARROWS, PRIVATE = _all()


def _fail_on(title: str, arrows: list[Arrow]) -> None:
    lines = list(dict.fromkeys(str(a) for a in sorted(arrows, key=lambda a: (a.source, a.line, a.target))))
    if lines:
        pytest.fail(f"{title} ({len(lines)}):\n  " + "\n  ".join(lines), pytrace=False)


def test_the_graph_sees_every_module():
    assert len(MODULES) > 100 and "mifacerf.capture.hardware.protocol" in MODULES
    assert "mifacerf.plugins.facerf_bsdf" in MODULES
    # relative imports from capture/ resolve under mifacerf.capture
    assert any(a.source.startswith("mifacerf.capture.") and a.target == "mifacerf.variant" for a in ARROWS)


def test_the_scanner_reads_relative_function_level_and_private_imports():
    text = (
        "from ..geometry import rigid\n"
        "from . import morph as M\n"
        "def f():\n"
        "    from ..rendering.api import _frame, load_model\n"
        "    import mifacerf.rendering.api\n"
        "    import mifacerf as mf\n"
        "    return M._private_helper(rigid.apply)\n"
    )
    arrows, private = arrows_of("mifacerf.registration.dots", text)
    assert {(a.target, a.line) for a in arrows} == {
        ("mifacerf.geometry.rigid", 1), ("mifacerf.registration.morph", 2), ("mifacerf.rendering.api", 4),
        ("mifacerf.rendering.api", 5), ("mifacerf", 6)}
    assert {(a.target, a.private) for a in private} == {("mifacerf.rendering.api", "_frame"),
                                                        ("mifacerf.registration.morph", "_private_helper")}
    assert str(private[0]).startswith("mifacerf/registration/dots.py:")


def test_every_package_has_a_floor():
    """A new sub-package of mifacerf is given its floor here (and in docs/architecture.md)."""
    top = {m.split(".")[1] for m in PACKAGES if m.count(".") >= 1}
    assert not top - set(FLOORS) - set(GROUND_PACKAGES), top - set(FLOORS) - set(GROUND_PACKAGES)


def test_ground_floor_imports_no_stage():
    bad = [a for a in ARROWS if floor(a.source) == 0 and floor(a.target) > 0]
    _fail_on("ground-floor modules importing a stage (or the facade)", bad)


def test_no_arrow_runs_up_the_pipeline():
    bad = [a for a in ARROWS if is_stage(a.source) and floor(a.target) > floor(a.source)]
    _fail_on("imports pointing to a later floor (" + " < ".join(FLOOR_NAMES) + "; an arrow to 'mifacerf' is "
             "to the package root, the facade: import the module itself, e.g. mifacerf.rendering.api)", bad)


def cyclic_arrows(arrows: list[Arrow]) -> list[Arrow]:
    """The arrows between stage packages that lie on a cycle of downward and sideways arrows.

    A cycle through an upward arrow is :func:`test_no_arrow_runs_up_the_pipeline`'s; this finds the
    cycles within a floor (capture <-> synthetic, rendering <-> plugins, evaluation <-> studio).
    """
    edges = defaultdict(list)
    for a in arrows:
        s, t = unit(a.source), unit(a.target)
        if s != t and is_stage(a.source) and is_stage(a.target) and floor(a.target) <= floor(a.source):
            edges[s, t].append(a)
    graph = defaultdict(set)
    for s, t in edges:
        graph[s].add(t)

    def reach(start):
        seen, todo = set(), [start]
        while todo:
            for n in graph[todo.pop()]:
                if n not in seen:
                    seen.add(n)
                    todo.append(n)
        return seen

    return [a for (s, t), group in edges.items() if s in reach(t) for a in group]


def test_cycle_finder():
    a = Arrow("mifacerf.capture.cli", "mifacerf.synthetic.synth", 1)
    b = Arrow("mifacerf.synthetic.olat", "mifacerf.capture.rig", 2)
    c = Arrow("mifacerf.tracking.record", "mifacerf.synthetic.olat", 3)
    assert cyclic_arrows([a, b, c]) == [a, b] and cyclic_arrows([a, c]) == []


def test_no_cycle_between_stage_packages():
    _fail_on("imports on a cycle between stage packages", cyclic_arrows(ARROWS))


def test_no_private_name_of_another_package():
    bad = [a for a in PRIVATE if unit(a.source) != unit(a.target)]
    _fail_on("uses of another package's underscore-private names", bad)
