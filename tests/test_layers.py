"""The import structure of docs/design.md: no module imports one higher in the chain, no cycles, and
the decision-level code and the reports import neither Lightning nor the model."""

import ast
from pathlib import Path

SRC = Path(__file__).resolve().parents[1] / "src" / "costseg"
# Packages (and top-level modules), lower layers first; each may import its own layer or lower.
# The command-line options (``options``) belong to the jobs: nothing below them imports them
# (the value types the lower layers check with are ``values``).
CHAIN = [
    {"atomic", "classes", "checkpoints", "progress", "values", "workers"},
    {"costs"},
    {"decision"},
    {"rules", "calibration"},
    {"data", "metrics", "models", "networks", "meta"},
    {"report", "compile_kernels"},
    {"evaluation", "prediction", "training", "export", "options"},
    {"cli", "api"},
]
NO_LIGHTNING = {"costs", "decision", "rules", "calibration", "metrics", "networks", "meta",
                "report", "evaluation", "prediction", "export", "workers",
                "compile_kernels", "api"}  # fmt: skip
NO_MODEL = {"costs", "decision", "rules", "calibration", "metrics", "meta", "report"}


def _imports() -> dict[str, set[str]]:
    """costseg module → the costseg (and lightning) modules it imports, anywhere in its code
    (``from package import module``: the module, not the package)."""
    paths = {
        ".".join(p.relative_to(SRC.parent).with_suffix("").parts).removesuffix(".__init__"): p
        for p in SRC.rglob("*.py")
    }
    found = {}
    for name, path in paths.items():
        names = set()
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and node.module:
                modules = {f"{node.module}.{a.name}" for a in node.names} & paths.keys()
                names.update(modules or {node.module})
            elif isinstance(node, ast.Import):
                names.update(a.name for a in node.names)
        found[name] = names
    return found


def _top(module: str) -> str:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else parts[0]


def _layer(name: str) -> int:
    return next(i for i, names in enumerate(CHAIN) if name in names)


def test_every_module_has_a_layer_and_imports_downwards():
    problems = []
    for module, targets in _imports().items():
        if module == "costseg":
            continue
        here = _layer(_top(module))
        for target in targets:
            if target.startswith("costseg.") and _layer(_top(target)) > here:
                problems.append(f"{module} imports {target}")
    assert not problems, problems


def test_light_layers_import_neither_lightning_nor_the_model():
    problems = []
    for module, targets in _imports().items():
        top = _top(module)
        for target in targets:
            if top in NO_LIGHTNING and target.split(".")[0] == "lightning":
                problems.append(f"{module} imports {target}")
            if top in NO_MODEL and target.startswith(("costseg.training.module", "costseg.models")):
                problems.append(f"{module} imports {target}")
    assert not problems, problems


def test_no_import_cycles_between_modules():
    imports = _imports()
    graph = {m: {t for t in ts if t in imports and t != m} for m, ts in imports.items()}
    # the package's own __getattr__ imports costseg.api on first use (costseg.evaluate): once the
    # package is loaded, so no module waits on another
    graph["costseg"] = set()
    state: dict[str, int] = {}

    def visit(node: str, path: list[str]) -> None:
        state[node] = 1
        for nxt in sorted(graph[node]):
            assert state.get(nxt) != 1, " -> ".join([*path, node, nxt])
            if nxt not in state:
                visit(nxt, [*path, node])
        state[node] = 2

    for node in sorted(graph):
        if node not in state:
            visit(node, [])


def test_files_stay_readable():
    """One job per file, at whatever length it needs; past ~600 lines, a warning to look again."""
    import warnings

    long = {str(p.relative_to(SRC)): n for p in SRC.rglob("*.py")
            if (n := len(p.read_text().splitlines())) > 600}  # fmt: skip
    if long:
        warnings.warn(f"files over 600 lines, is each one job? {long}", stacklevel=1)


def test_no_private_names_across_modules_and_no_fallback_imports():
    """No private name (``_x``) imported from another module; a ``try: import`` only to turn a
    missing optional extra into a clear error (its handler raises), never to fall back."""
    problems = []
    for path in SRC.rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("costseg"):
                private = [a.name for a in node.names if a.name.startswith("_")]
                problems += [f"{path.relative_to(SRC)} imports {n}" for n in private]
            if isinstance(node, ast.Try) and any(
                isinstance(s, (ast.Import, ast.ImportFrom)) for s in node.body
            ):
                raises = all(any(isinstance(s, ast.Raise) for s in h.body) for h in node.handlers)
                if not raises:
                    problems.append(f"{path.relative_to(SRC)}:{node.lineno} falls back")
    assert not problems, problems


def test_evaluation_imports_no_lightning_at_run_time(imported):
    """evaluate.py runs a plain nn.Module: Lightning (9 s to import on 2 cores) stays out."""
    assert "lightning" not in imported["an evaluation"]


def test_few_modules_at_the_top_level():
    """The lowest layer's modules, the command line's (options, cli, api) and the kernels'
    compiler; a package for anything more."""
    top = sorted(p.name for p in SRC.glob("*.py") if p.name != "__init__.py")
    assert len(top) <= 11, top


def test_configs_live_once_at_the_top():
    """configs/ at the repository's top is what the package reads; src/costseg/configs links it."""
    from costseg import CONFIGS

    top = SRC.parents[1] / "configs"
    assert (SRC / "configs").is_symlink() and (SRC / "configs").resolve() == top
    assert Path(str(CONFIGS)).resolve() == top and (top / "costs" / "egoistic.yaml").is_file()


OPTIONS_READERS = {
    "costseg.cli",  # the command lines
    "costseg.api",  # the Python API: the options of its keywords
    "costseg.options",
    "costseg.evaluation.run",  # evaluate(opts): plans, then runs the plan
    "costseg.evaluation.plan",
    "costseg.evaluation.checks",
    "costseg.evaluation.settings",  # each analysis's settings, resolved once by the plan
    "costseg.evaluation.analyses",  # the table of the analyses and their resolvers
    "costseg.networks.protocols",  # the inference protocol of every job's network options
    "costseg.prediction.job",  # predict.py's own plan
    "costseg.export.job",  # export.py's own plan
}
"""The modules that may read an options object of :mod:`costseg.options`: the command lines,
the checks and the plans. Below the plan, the loop, the analyses and the reports read the plan,
the analyses' settings and the results."""


def _reads_options(path: Path) -> list[str]:
    """Where the module at ``path`` names an options dataclass or reads an ``opts`` /
    ``options`` object."""
    found = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module == "costseg.options":
            found += [f"imports {a.name}" for a in node.names if a.name.endswith("Options")]
        elif isinstance(node, ast.Name) and node.id == "opts":
            found.append(f"line {node.lineno}: opts")
        elif isinstance(node, ast.Attribute) and node.attr in ("opts", "options"):
            if isinstance(node.ctx, ast.Store):  # PyAV's stream options, set
                continue
            found.append(f"line {node.lineno}: .{node.attr}")
    return found


def test_nothing_below_the_plan_reads_the_options():
    readers = {}
    for path in SRC.rglob("*.py"):
        module = ".".join(path.relative_to(SRC.parent).with_suffix("").parts)
        module = module.removesuffix(".__init__")
        if module in OPTIONS_READERS or module.startswith(("costseg.training",)):
            continue
        if found := _reads_options(path):
            readers[module] = found
    assert not readers


def test_the_options_check_finds_a_reader(tmp_path):
    reader = tmp_path / "reader.py"
    reader.write_text("def f(plan):\n    return plan.options.seed\n")
    assert _reads_options(reader) == ["line 2: .options"]
