"""The package's layers (docs/architecture.md), checked on the source: every import of every
module, those inside functions included, must go down or sideways within its own part.

ground   errors, io, metrics, landmarks, landmark_tables, geometry, imaging, provenance, contract, artifact, ops,
         progress, neutral, faps, shape_space, retarget, videofile
stages   data; model (data); regressors; sadm (data, model, regressors); eri (data, model, regressors);
         mesh (data); codec (data): siblings never import each other
runtime  torch-free: the runtime, the data layer and the ground only
top      eval, runs (runs/train_cli: facesynth train), onnx, batch, web, the CLIs (facesynth.cli and every ``cli`` /
         ``*_cli`` module); facesynth/conf holds the Hydra yaml, no module
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "facesynth"

GROUND = {"facesynth", "errors", "io", "metrics", "landmarks", "landmark_tables", "geometry", "imaging", "provenance",
          "contract", "artifact", "ops", "progress", "neutral", "faps", "shape_space", "retarget", "videofile"}
TOP = {"eval", "runs", "onnx", "batch", "web", "cli", "__main__"}
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
TORCH_FREE = {"runtime", "contract", "landmarks", "landmark_tables", "errors", "io", "imaging", "geometry", "metrics",
              "provenance", "progress", "videofile", "facesynth"}


def part(module: str) -> str:
    """The layer part of a dotted module name under ``facesynth``."""
    names = module.split(".")
    leaf = names[-1]
    if leaf == "cli" or leaf.endswith("_cli") or leaf == "__main__":
        return "top"
    top = names[1] if len(names) > 1 else "facesynth"
    if top in GROUND:
        return "ground"
    if top in TOP:
        return "top"
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


def violations(sources: dict[str, str]) -> list[str]:
    """Every import in ``sources`` (dotted module name -> source) that breaks the layers."""
    bad = []
    for module, source in sorted(sources.items()):
        me = part(module)
        if me == "top":
            continue
        allowed = {me, "ground"} | ALLOWED.get(me, set())
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


@pytest.mark.parametrize("module,source,culprit", [
    ("facesynth.sadm.bad", "from facesynth.eri.faps import compute_faps\n", "facesynth.eri.faps"),
    ("facesynth.model.bad", "def f():\n    from facesynth.eval.report import write_plots\n", "facesynth.eval.report"),
    ("facesynth.data.bad", "import facesynth.model.pca\n", "facesynth.model.pca"),
    ("facesynth.mesh.bad", "from facesynth.codec import geometry\n", "facesynth.codec"),
    ("facesynth.runtime.bad", "def f():\n    from facesynth.onnx.synthesis import export_run\n", "facesynth.onnx.synthesis"),
    ("facesynth.metrics", "from facesynth.data import load_sequence\n", "facesynth.data"),
    ("facesynth.codec.bad", "from ..runs import config\n", "facesynth.runs"),
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


def test_no_module_over_400_lines():
    long = {m: n for m, s in package_sources().items() if (n := s.count("\n")) > 400}
    assert long == {}
