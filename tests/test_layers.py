"""The package's layers (docs/architecture.md), checked on the source: every import of every
module, those inside functions included, must go down or sideways within its own part.

ground   errors, io, metrics, landmarks, landmark_tables, geometry, compositing, provenance, contract, artifact, ops,
         progress, neutral, coverage, faps, shape_space, retarget, videofile, sheet
stages   data; model (data); regressors; sadm (data, model, regressors); eri (data, model, regressors);
         mesh (data); codec (data): siblings never import each other
runtime  torch-free: the runtime, the data layer and the ground only
top      the top floor, in ranks; a part imports its own rank's part and those below, never a sibling:
           rundir   run-folder access (layout, config, data, the synthesizer)
           onnx     export (the export API: onnx/export; the avatar's metadata: onnx/avatar)
           eval     evaluation and reports (the talking head's figures read onnx/avatar)
           runs     training (Hydra configs, the training job, the run folder's lock)
           batch, web   many runs at once; the local pages and their jobs
           cli      the command lines: facesynth.cli, __main__ and every ``cli`` / ``*_cli`` module
facesynth/conf holds the Hydra yaml, no module. No module imports itself back through others (no cycle).
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "facesynth"

GROUND = {"facesynth", "errors", "io", "metrics", "landmarks", "landmark_tables", "geometry", "compositing", "provenance",
          "contract", "artifact", "ops", "progress", "neutral", "coverage", "faps", "shape_space", "retarget", "videofile", "sheet"}
# the top floor, lowest first: a part may import the parts of lower ranks (and the stages and the ground)
TOP_RANKS = [{"rundir"}, {"onnx"}, {"eval"}, {"runs"}, {"batch", "web"}, {"cli"}]
RANK = {p: i for i, parts in enumerate(TOP_RANKS) for p in parts}
# what each part may import besides itself and the ground
ALLOWED = {
    "ground": set(),
    "data": set(),
    "model": {"data"},
    "regressors": set(),
    "sadm": {"data", "model", "regressors"},
    "eri": {"data", "model", "regressors"},
    "mesh": {"data"},
    "codec": {"data"},
    "runtime": {"data"},
}
TORCH_FREE = {"runtime", "contract", "landmarks", "landmark_tables", "errors", "io", "compositing", "geometry", "metrics",
              "provenance", "progress", "videofile", "sheet", "facesynth"}


def part(module: str) -> str:
    """The layer part of a dotted module name under ``facesynth``."""
    names = module.split(".")
    leaf = names[-1]
    if leaf == "cli" or leaf.endswith("_cli") or leaf == "__main__":
        return "cli"
    top = names[1] if len(names) > 1 else "facesynth"
    if top in GROUND:
        return "ground"
    return top


def imports(module: str, source: str) -> list[tuple[str, int]]:
    """Internal modules imported anywhere in ``source`` (nested imports included), with lines."""
    out = []
    is_pkg = module.endswith(".__init__")
    base = module.rsplit(".", 1)[0] if not is_pkg else module[: -len(".__init__")]
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            out += [(a.name, node.lineno) for a in node.names if a.name.split(".")[0] == "facesynth"]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                anchor = base.split(".")
                anchor = anchor[: len(anchor) - (node.level - 1)] if node.level > 1 else anchor
                target = ".".join(anchor + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            if target.split(".")[0] == "facesynth":
                out.append((target, node.lineno))
    return out


def allowed_parts(me: str) -> set[str]:
    """The parts that part ``me`` may import."""
    if me in RANK:  # the top floor: everything below it, and the lower ranks of its own
        return {me, "ground", *ALLOWED} | {p for p in RANK if RANK[p] < RANK[me]}
    return {me, "ground"} | ALLOWED.get(me, set())


def violations(sources: dict[str, str]) -> list[str]:
    """Every import in ``sources`` (dotted module name -> source) that breaks the layers."""
    bad = []
    for module, source in sorted(sources.items()):
        me = part(module)
        if me == "cli":
            continue
        allowed = allowed_parts(me)
        for target, line in imports(module, source):
            other = part(target)
            if other not in allowed:
                bad.append(f"{module}:{line} ({me}) imports {target} ({other})")
    return bad


def package_sources() -> dict[str, str]:
    out = {}
    for path in sorted(PACKAGE.rglob("*.py")):
        rel = path.relative_to(PACKAGE.parent).with_suffix("")
        name = ".".join(rel.parts)
        out[name.removesuffix(".__init__") if name.endswith(".__init__") else name] = path.read_text()
    return out


def test_package_layers_hold():
    assert violations(package_sources()) == []


def test_every_part_has_a_place():
    """A new top-level module or package is placed in a layer before it can import anything."""
    known = {"ground", *ALLOWED, *RANK}
    assert {part(m) for m in package_sources()} <= known


def cycles(sources: dict[str, str]) -> list[list[str]]:
    """The import cycles among ``sources``' modules (each import of ``a.b.c`` counts as one of
    its deepest module in ``sources``), as Tarjan's strongly connected components of 2+ modules."""
    graph = {}
    for module, source in sources.items():
        targets = set()
        for target, _ in imports(module, source):
            while target and target not in sources:
                target = target.rpartition(".")[0]
            if target and target != module and target != "facesynth" and not module.startswith(target + "."):
                targets.add(target)  # a module importing its own package's __init__ is not a cycle
        graph[module] = targets
    index, low, stack, on, out = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def test_no_import_cycle():
    assert cycles(package_sources()) == []


def test_the_old_top_floor_cycle_is_caught():
    """runs/training -> eval/talking_head -> onnx/avatar -> runs/rundir: a cycle and two ranks broken."""
    sources = {"facesynth.runs.training": "from facesynth.eval.talking_head import talking_head_figures\n",
               "facesynth.eval.talking_head": "from facesynth.onnx.avatar import avatar_metadata\n",
               "facesynth.onnx.avatar": "def f():\n    from facesynth.runs.training import train\n"}
    assert cycles(sources) == [sorted(sources)]
    found = violations(sources)
    assert len(found) == 1 and "facesynth.onnx.avatar" in found[0] and "(runs)" in found[0]


@pytest.mark.parametrize("module,source,culprit", [
    ("facesynth.sadm.bad", "from facesynth.eri.faps import compute_faps\n", "facesynth.eri.faps"),
    ("facesynth.model.bad", "def f():\n    from facesynth.eval.report import write_plots\n", "facesynth.eval.report"),
    ("facesynth.data.bad", "import facesynth.model.pca\n", "facesynth.model.pca"),
    ("facesynth.mesh.bad", "from facesynth.codec import geometry\n", "facesynth.codec"),
    ("facesynth.runtime.bad", "def f():\n    from facesynth.onnx.synthesis import export_run\n", "facesynth.onnx.synthesis"),
    ("facesynth.metrics", "from facesynth.data import load_sequence\n", "facesynth.data"),
    ("facesynth.codec.bad", "from ..runs import config\n", "facesynth.runs"),
    ("facesynth.rundir", "from facesynth.eval.report import legend_lines\n", "facesynth.eval.report"),
    ("facesynth.onnx.bad", "def f():\n    from facesynth.runs.training import train\n", "facesynth.runs.training"),
    ("facesynth.onnx.bad", "from facesynth.eval.strip import box_tile\n", "facesynth.eval.strip"),
    ("facesynth.eval.bad", "from facesynth.runs.config import EvalConfig\n", "facesynth.runs.config"),
    ("facesynth.runs.bad", "from facesynth.batch.job import run_job\n", "facesynth.batch.job"),
    ("facesynth.batch.bad", "from facesynth.web.studio_job import Job\n", "facesynth.web.studio_job"),
    ("facesynth.web.bad", "from facesynth.onnx.cli import run\n", "facesynth.onnx.cli"),
])
def test_a_forbidden_import_is_caught(module, source, culprit):
    """A synthetic module with one forbidden import (top level, inside a function, relative)."""
    sources = {**package_sources(), module: source}
    found = violations(sources)
    assert len(found) == 1 and culprit in found[0] and module in found[0]


@pytest.mark.parametrize("module,source", [
    ("facesynth.sadm.ok", "from facesynth.model.face_model import FaceModel\nfrom facesynth.metrics import psnr\n"),
    ("facesynth.codec.cli", "from facesynth.mesh.io import load_mesh\n"),  # CLIs sit on top
    ("facesynth.runtime.ok", "from facesynth.data.readers import load_landmarks\n"),
    ("facesynth.eval.ok", "from facesynth.onnx.avatar import avatar_metadata\nfrom facesynth.rundir import run_data\n"),
    ("facesynth.batch.ok", "from facesynth.runs.training import train\nfrom facesynth.onnx.export import export_model\n"),
    ("facesynth.web.ok", "from facesynth.runs.config import DataConf\n"),
])
def test_allowed_imports_pass(module, source):
    assert violations({module: source}) == []


def test_runtime_never_imports_torch_even_indirectly():
    """The runtime's import closure (module-level and nested imports) holds no torch."""
    sources = package_sources()
    seen, stack = set(), [m for m in sources if part(m) == "runtime"]
    while stack:
        m = stack.pop()
        if m in seen or m not in sources:
            continue
        seen.add(m)
        tree = ast.parse(sources[m])
        for node in ast.walk(tree):
            names = [a.name for a in node.names] if isinstance(node, ast.Import) else \
                [node.module or ""] if isinstance(node, ast.ImportFrom) and not node.level else []
            assert not any(n.split(".")[0] in {"torch", "kornia"} for n in names), f"{m} imports torch"
        for target, _ in imports(m, sources[m]):
            parts = target.split(".")
            stack += [".".join(parts[:i]) for i in range(2, len(parts) + 1)]
    assert any(part(m) == "runtime" for m in seen)


LONG = 400  # lines: past this, a module says in its docstring why its one concept needs them


def test_a_long_module_says_why():
    """A module holds one concept, however long that takes: size is no reason to split one
    (a split by size leaves two halves that import each other: test_no_import_cycle) nor to
    keep a concept in one. A module past ``LONG`` lines says in its docstring what makes the
    one concept long, in a sentence that ends "hence its length"."""
    unexplained = []
    for module, source in package_sources().items():
        doc = ast.get_docstring(ast.parse(source)) or ""
        if source.count("\n") > LONG and "hence its length" not in " ".join(doc.split()):
            unexplained.append(module)
    assert unexplained == []
