"""The package's layering: every module imports only downward (no import cycle, counting the imports
inside functions, which would otherwise hide one), and only the command line and the campaign itself
import the experiment campaign (`cvqpg.campaign`)."""

import ast
from pathlib import Path

import cvqpg

CAMPAIGN = "cvqpg.campaign"
CAMPAIGN_IMPORTERS = ("cvqpg.cli",)

ROOT = Path(cvqpg.__file__).parent


def module_name(path: Path) -> str:
    parts = path.relative_to(ROOT.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


MODULES = {module_name(path): path for path in sorted(ROOT.rglob("*.py"))}


def imported_modules(name: str, path: Path) -> set[str]:
    """The modules that `name` imports anywhere in its source, relative imports resolved; `from P import x`
    counts as importing the module P.x where the package has one, else P."""
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parts = package.split(".")
                base = ".".join(parts[:len(parts) - node.level + 1] + ([base] if base else []))
            for alias in node.names:
                found.add(f"{base}.{alias.name}" if f"{base}.{alias.name}" in MODULES else base)
    return found - {name}


IMPORTS = {name: imported_modules(name, path) for name, path in MODULES.items()}
GRAPH = {name: imported & set(MODULES) for name, imported in IMPORTS.items()}


def reachable(graph: dict[str, set[str]], start: str) -> set[str]:
    """The nodes that paths from `start` lead to."""
    seen, todo = set(), [start]
    while todo:
        for successor in graph[todo.pop()] - seen:
            seen.add(successor)
            todo.append(successor)
    return seen


def cycle_edges(graph: dict[str, set[str]]) -> set[tuple[str, str]]:
    """Every edge on a cycle: a → b where a can be reached again from b."""
    return {(a, b) for a, successors in graph.items() for b in successors if a in reachable(graph, b)}


def test_the_import_graph_is_found():
    assert {"cvqpg.codec", "cvqpg.storage", "cvqpg.ops.rasterize", "cvqpg.campaign.bench"} <= set(MODULES)
    assert "cvqpg.codec" in GRAPH["cvqpg.storage"] and "cvqpg.ops" in GRAPH["cvqpg.ops.field"]
    assert "cvqpg.ops.rasterize.gpu" in GRAPH["cvqpg.ops.rasterize"]  # imported inside a function


def test_every_import_within_the_package_names_one_of_its_modules():
    missing = {(name, module) for name, imported in IMPORTS.items() for module in imported
               if module.split(".")[0] == "cvqpg" and module not in MODULES}
    assert missing == set(), "(importer, missing module)"


def test_no_import_cycles():
    assert cycle_edges(GRAPH) == set(), "import cycle through these edges (importer, imported)"


def test_a_cycle_is_found():
    assert cycle_edges({"a": {"b"}, "b": {"c", "d"}, "c": {"a"}, "d": set()}) == {("a", "b"), ("b", "c"), ("c", "a")}


def test_only_the_command_line_and_the_campaign_import_the_campaign():
    importers = {name for name, imported in GRAPH.items() if any(m.startswith(CAMPAIGN) for m in imported)}
    assert {name for name in importers if not name.startswith(CAMPAIGN)} <= set(CAMPAIGN_IMPORTERS)


def test_the_codec_and_storage_sit_below_the_workflows():
    assert GRAPH["cvqpg.codec"] <= {"cvqpg.bitdepths", "cvqpg.config", "cvqpg.defaults", "cvqpg.display",
                                    "cvqpg.errors", "cvqpg.phase", "cvqpg.primitives"}
    assert GRAPH["cvqpg.storage"] <= {"cvqpg.codec", "cvqpg.config", "cvqpg.errors", "cvqpg.files",
                                      "cvqpg.primitives", "cvqpg.representation"}
    assert not any(name.startswith("cvqpg.app") or name in MODEL_FILE_LAYERS
                   for name in reachable(GRAPH, "cvqpg.representation"))
    assert "cvqpg.search" not in GRAPH["cvqpg.finetune"] | GRAPH["cvqpg.runs"]


# The modules that read, write and compress model files, each importing only those before it; storage alone
# decides a file's format (safetensors or the .cvq codec) when it reads one.
MODEL_FILE_LAYERS = ("cvqpg.storage", "cvqpg.runs", "cvqpg.finetune", "cvqpg.search", "cvqpg.app.compression",
                     "cvqpg.app.encoding")


def test_the_model_file_workflows_import_one_way():
    """The circle storage/runs → workflows → runs/storage/finetune → workflows must not come back, not even
    through an import inside a function."""
    within = {name: GRAPH[name] & set(MODEL_FILE_LAYERS) for name in MODEL_FILE_LAYERS}
    assert cycle_edges(within) == set()
    upward = {(name, imported) for index, name in enumerate(MODEL_FILE_LAYERS)
              for imported in within[name] if imported in MODEL_FILE_LAYERS[index:]}
    assert upward == set(), "(importer, a module above it)"


def test_a_cycle_among_the_model_file_workflows_would_be_found():
    graph = {name: set(GRAPH[name]) for name in GRAPH}
    graph["cvqpg.storage"].add("cvqpg.app.compression")  # as a loader importing the workflow once did
    assert ("cvqpg.storage", "cvqpg.app.compression") in cycle_edges(graph)


def test_only_storage_reads_and_writes_safetensors():
    readers = {name for name, imported in IMPORTS.items() if any(m.split(".")[0] == "safetensors" for m in imported)}
    assert readers == {"cvqpg.storage"}


APP = "cvqpg.app"


def test_the_core_never_imports_the_application_layer_or_the_command_line():
    """Compilation, provenance and memory tracking belong to the commands, not to a library call."""
    core = {name for name in GRAPH if not name.startswith((APP, CAMPAIGN, "cvqpg.cli"))}
    assert {name: sorted(m for m in GRAPH[name] if m.startswith((APP, "cvqpg.cli"))) for name in core
            if any(m.startswith((APP, "cvqpg.cli")) for m in GRAPH[name])} == {}
    assert {"cvqpg.fitting", "cvqpg.runs", "cvqpg.ops"} <= core


def test_the_command_line_only_parses_calls_and_prints():
    """`cli.py` refuses nothing itself beyond argparse's types (every check is the application's, which a caller
    of the library meets too) and writes through nothing: its plans, checks and workflows live in `cvqpg.app`."""
    tree = ast.parse(MODULES["cvqpg.cli"].read_text())
    raising = {function.name for function in ast.walk(tree) if isinstance(function, ast.FunctionDef)
               for node in ast.walk(function) if isinstance(node, ast.Raise) and node.exc is not None}
    assert raising <= {"finite", "whole"}, "functions of cli.py that raise: move their checks to cvqpg.app"
    writers = {"cvqpg.app.outputs", "cvqpg.files", "cvqpg.runs", "cvqpg.storage", "cvqpg.fitting"}
    assert GRAPH["cvqpg.cli"] & writers == set()
