"""The layers of design.md and the one-home rules of issue 19, checked by parsing the package's source.

Layers, one folder each at the repository's root, all installed inside envisat_pose: core (envisat_pose/*.py)
imports nothing above it; a stage (datagen, perception, filtering, analysis) imports only the core, never another
stage, a pipeline or the app; a pipeline (pipelines/) imports the core and the stages, never the app; the app
(app/) imports anything. Imports inside
functions count too, and so do relative imports and the old top-level names. No two modules import each other,
directly or around a loop, even inside functions (0 import cycles); an import inside a function defers a heavy
third-party module, else it stands at the top of its module.

One home for each concept: the state's slices are defined only in envisat_pose/state.py; manifest.json is
written only by the core's resumable-job protocol (envisat_pose/resumable.py); shards are read (a tar opened for
reading) only by envisat_pose/shard_reader.py; a verb or pipeline resolves its config only through
config.resolve_job_config (never by merging layers itself); a chi-square gate comes from its probability
(envisat_pose.gates), never typed as a number, and so does a band of NEES or NIS (scipy.stats.chi2, as
analysis.stats.chi2_mean_bounds computes it); a weights file's metadata keys are typed only in
perception/weights_keys.py; the package counts the machine's cores only in envisat_pose/pools.py (usable_cores:
the affinity and a cgroup quota too; a default on os.cpu_count() alone oversubscribed a container). The benches
and the scripts are read for every one-home rule but that last (they record the machine); they
import no verb (the job a verb runs is the library's). A verb file stays thin: at most VERB_MAX_LINES lines.
Every command line takes whole flags only (envisat_pose/whole_flags.py: no argparse parser that abbreviates).
Each checker runs on a source string, so the tests below show it catching a planted copy.
"""

import ast
import functools
import os
import re

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
STAGES = ("datagen", "perception", "filtering", "analysis")
UPPER = ("app", "pipelines")  # the layers above the stages
# where each layer's files live in the repository (a folder at the root), and their import name
LAYOUT = {"envisat_pose": "envisat_pose", **{s: f"envisat_pose.{s}" for s in STAGES + UPPER}}
# scanned for every one-home rule besides the package (the benches and the scripts are code people copy from)
EXTRA_FOLDERS = ("bench", "scripts")


# Each file's tree is parsed once and walked once per process: the checks below read the same ~250 files many times
# over (parse and ast.walk were two thirds of this file's time). Trees are read, never changed.
@functools.lru_cache(maxsize=None)
def parse(source: str, filename: str = "<unknown>") -> ast.Module:
    """ast.parse, memoized on the source text."""
    return ast.parse(source, filename)


@functools.lru_cache(maxsize=None)
def walk(node: ast.AST) -> tuple[ast.AST, ...]:
    """ast.walk's nodes as a tuple, memoized on the node (AST nodes hash by identity)."""
    return tuple(ast.walk(node))


# the kinds whose checker reads the tests' helpers too (a test must not build its own physics for the filter)
WITH_TESTS = ("physics_builders", "hand_built_runs")
THIS_FILE = os.path.join("tests", "test_architecture.py")

# Copies that other engineers are removing now (issue 19). An entry must name a file that still holds the
# copy: `test_pending_copies_are_still_there` fails once it is gone, so the entry is deleted with the fix.
PENDING = {
    "state_slices": {},
    "manifest_writers": {},
    "hand_resolved_configs": {},
    "physics_builders": {},
    "typed_gates": {},
    "shard_readers": {},
    "hand_built_runs": {},
    "typed_bands": {},
    "app_imports": {},
    "typed_weights_keys": {},
    "machine_counts": {},
    "npz_readers": {},
}


def source_files(root: str = ROOT):
    """(path, module name) of every .py file of the package: the core (envisat_pose/, its own files only) and
    the folders of the stages, pipelines/ and app/, mapped into envisat_pose (a folder missing is skipped)."""
    for folder, package in LAYOUT.items():
        for dirpath, dirnames, filenames in os.walk(os.path.join(root, folder)):
            dirnames[:] = [d for d in dirnames if d != "__pycache__"]
            rel_dir = os.path.relpath(dirpath, root)
            if folder == "envisat_pose" and rel_dir != "envisat_pose":
                continue
            for name in filenames:
                if name.endswith(".py"):
                    path = os.path.join(dirpath, name)
                    rel = os.path.relpath(path, os.path.join(root, folder))[:-3].replace(os.sep, ".")
                    mod = package if rel == "__init__" else f"{package}.{rel.removesuffix('.__init__')}"
                    yield path, mod


def checked_files(root: str = ROOT, extra=EXTRA_FOLDERS):
    """Repository-relative paths of the package's files and those of the extra folders (benches, scripts)."""
    paths = [os.path.relpath(p, root) for p, _ in source_files(root)]
    for folder in extra:
        for dirpath, _, filenames in os.walk(os.path.join(root, folder)):
            paths += [os.path.relpath(os.path.join(dirpath, f), root) for f in filenames if f.endswith(".py")]
    return sorted(paths)


def imported_modules(path: str, module: str, source: str | None = None) -> list[tuple[int, str]]:
    """Every module an import statement in the file names, relative imports resolved."""
    tree = parse(source if source is not None else open(path, encoding="utf-8").read(), path)
    is_pkg = path.endswith("__init__.py")
    out = []
    for node in walk(tree):
        if isinstance(node, ast.Import):
            out += [(node.lineno, a.name) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = module.split(".")
                base = base[: len(base) - node.level + (1 if is_pkg else 0)]
                name = ".".join(base + ([node.module] if node.module else []))
            else:
                name = node.module or ""
            out.append((node.lineno, name))
            out += [(node.lineno, f"{name}.{a.name}") for a in node.names]  # `from pkg import stage`
    return out


def layer_of(module: str) -> str | None:
    """'app', 'pipelines', a stage name, 'core', a forbidden bare stage name ('bare:...'), or None (not ours)."""
    parts = module.split(".")
    if parts[0] in STAGES:
        return f"bare:{parts[0]}"
    if parts[0] != "envisat_pose":
        return None
    if len(parts) > 1 and parts[1] in UPPER:
        return parts[1]
    if len(parts) > 1 and parts[1] in STAGES:
        return parts[1]
    return "core"


def crossing(own: str, other: str) -> str | None:
    """Why a module of layer `own` may not import one of layer `other` (None: it may)."""
    if other.startswith("bare:"):
        return "the stages install inside envisat_pose"
    if other == own or own == "app":
        return None
    if own == "core" and other != "core":
        return "the core imports nothing above it"
    if own in STAGES and other != "core":
        return "a stage imports only the core"
    if own == "pipelines" and other == "app":
        return "a pipeline imports the core and the stages, never the app"
    return None


def violations() -> list[str]:
    found = []
    for path, module in source_files():
        own = layer_of(module)
        for line, name in imported_modules(path, module):
            other = layer_of(name)
            why = None if other is None else crossing(own, other)
            if why:
                found.append(f"{os.path.relpath(path, ROOT)}:{line} imports {name}: {why}")
    return found


# ---------------------------------------------------------------- no import cycles

def module_graph(root: str = ROOT) -> dict[str, set[str]]:
    """{module: the package's modules it imports}, imports inside functions included: each imported name resolved
    to the longest prefix that is one of the package's modules (`from envisat_pose.pipelines import jobs` is jobs)."""
    files = {module: path for path, module in source_files(root)}
    graph = {}
    for module, path in files.items():
        deps = set()
        for _, name in imported_modules(path, module):
            parts = name.split(".")
            target = next((".".join(parts[:k]) for k in range(len(parts), 0, -1) if ".".join(parts[:k]) in files),
                          None)
            if target is not None and target != module:
                deps.add(target)
        graph[module] = deps
    return graph


def import_cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The graph's strongly connected components of more than one module (Tarjan's algorithm, iterative): each is
    a set of modules that import one another, at import time or inside a function. Sorted, for the message."""
    index, low, on_stack, stack, found = {}, {}, set(), [], []
    for start in sorted(graph):
        if start in index:
            continue
        work = [(start, iter(sorted(graph[start])))]
        index[start] = low[start] = len(index)
        stack.append(start)
        on_stack.add(start)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = len(index)
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(graph.get(child, ())))))
                elif child in on_stack:
                    low[node] = min(low[node], index[child])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                component = []
                while True:
                    m = stack.pop()
                    on_stack.discard(m)
                    component.append(m)
                    if m == node:
                        break
                if len(component) > 1:
                    found.append(sorted(component))
    return sorted(found)


# ---------------------------------------------------------------- lazy imports defer something heavy

# third-party modules whose import costs time, memory or a GL / thread set-up that must come first
HEAVY = frozenset({"torch", "mujoco", "cv2", "rerun", "dask", "distributed", "OpenGL", "numba", "scipy",
                   "matplotlib", "safetensors", "webdataset", "filterpy", "pycocotools"})


def split_imports(path: str, module: str, source: str | None = None):
    """([(line, name)] of the module-level imports, [(line, [names])] of each import inside a function), names
    resolved as `imported_modules` does (a `from` import also names `module.name`)."""
    tree = parse(source if source is not None else open(path, encoding="utf-8").read(), path)
    is_pkg = path.endswith("__init__.py")
    top, inner = [], []

    def names(node):
        if isinstance(node, ast.Import):
            return [a.name for a in node.names]
        base = node.module or ""
        if node.level:
            parts = module.split(".")
            base = ".".join(parts[: len(parts) - node.level + (1 if is_pkg else 0)] + ([base] if base else []))
        return [base] + [f"{base}.{a.name}" for a in node.names]

    def visit(node, in_function):
        for child in ast.iter_child_nodes(node):
            if isinstance(child, (ast.Import, ast.ImportFrom)):
                if in_function:
                    inner.append((child.lineno, names(child)))
                else:
                    top.extend((child.lineno, n) for n in names(child))
            visit(child, in_function or isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)))

    visit(tree, False)
    return top, inner


def needless_lazy_imports(root: str = ROOT) -> list[str]:
    """Imports of the package's own modules inside a function that defer no heavy third-party module: the
    imported module pulls in (at import time, through the package's own module-level imports) nothing of HEAVY
    that the importing module does not pull in already. Such an import hides a dependency for no gain."""
    files = {module: path for path, module in source_files(root)}

    def own(name):
        parts = name.split(".")
        return next((".".join(parts[:k]) for k in range(len(parts), 0, -1) if ".".join(parts[:k]) in files), None)

    deps, heavy, inner = {}, {}, {}
    for module, path in files.items():
        top, inner[module] = split_imports(path, module)
        parents = {".".join(module.split(".")[:k]) for k in range(1, module.count(".") + 1)}
        deps[module] = {own(n) for _, n in top} - {None, module} | (parents & set(files))
        heavy[module] = {n.split(".")[0] for _, n in top if own(n) is None and n.split(".")[0] in HEAVY}

    @functools.cache
    def pulled(module):
        seen, todo, found = {module}, [module], set()
        while todo:
            m = todo.pop()
            found |= heavy[m]
            todo += [d for d in deps[m] if d not in seen]
            seen |= deps[m]
        return frozenset(found)

    found = []
    for module, imports in inner.items():
        for line, names in imports:
            targets = {own(n) for n in names} - {None, module}
            if targets and not set().union(*(pulled(t) for t in targets)) - pulled(module):
                found.append(f"{os.path.relpath(files[module], root)}:{line} imports {sorted(targets)} inside a "
                             f"function, which defers nothing heavy")
    return sorted(found)


def test_lazy_imports_only_defer_heavy_modules():
    """An import inside a function is kept for a heavy third-party module (torch, mujoco, OpenCV, Rerun, Dask,
    OpenGL...), directly or through the package's module that pulls it in; any other import stands at the top
    of its module, where a reader sees the dependency (floor: 0)."""
    assert needless_lazy_imports() == []


def test_the_lazy_import_checker_sees_a_needless_one_and_keeps_a_heavy_one(tmp_path):
    (tmp_path / "pipelines").mkdir()
    (tmp_path / "pipelines" / "light.py").write_text("import numpy\n")
    (tmp_path / "pipelines" / "heavy.py").write_text("import torch\n")
    (tmp_path / "pipelines" / "user.py").write_text(
        "def f():\n    from envisat_pose.pipelines.light import x\n\n"
        "def g():\n    from . import heavy\n")
    (tmp_path / "pipelines" / "has_torch.py").write_text(
        "import torch\n\ndef h():\n    from envisat_pose.pipelines import heavy\n")
    found = needless_lazy_imports(str(tmp_path))
    assert [f.split(" imports")[0] for f in found] == [os.path.join("pipelines", "has_torch.py") + ":4",
                                                       os.path.join("pipelines", "user.py") + ":2"]


# ---------------------------------------------------------------- one name per concept

# the verbs' protocol: app/cli.py calls each verb module's register, and each verb resolves its config in
# resolve_config; one name on purpose
VERB_PROTOCOL = ("register", "resolve_config")
# Collisions that are still to be renamed (issue 50, item 4). An entry must still collide:
# `test_pending_collisions_are_still_there` fails once it is gone, so the entry is deleted with the rename.
PENDING_COLLISIONS: set[str] = set()


def public_names(root: str = ROOT) -> dict[str, list[str]]:
    """{name: the modules that define it}: every public (no leading underscore) function or class at a module's
    top level, and as 'module:NAME' every public one named like another module of the package (a function
    `pseudo_labels` beside the module pseudo_labels.py; a module's main function named like it is not one)."""
    found: dict[str, list[str]] = {}
    modules = {}
    for path, module in source_files(root):
        modules.setdefault(module.rsplit(".", 1)[-1], []).append(module)
        for node in parse(open(path, encoding="utf-8").read(), path).body:
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)) and not node.name.startswith("_"):
                found.setdefault(node.name, []).append(module)
    for name, where in list(found.items()):
        own = any(m.rsplit(".", 1)[-1] == name for m in where)  # a module's main function: estimate.estimate
        others = [m for m in modules.get(name, []) if m not in where]
        if others and not own:
            found[f"module:{name}"] = sorted(where + others)
    return found


def collisions(root: str = ROOT) -> dict[str, list[str]]:
    """{name: modules} of the public names defined in more than one module (or named like another module),
    the verbs' protocol apart."""
    return {name: sorted(where) for name, where in public_names(root).items()
            if (len(where) > 1 or name.startswith("module:")) and name not in VERB_PROTOCOL}


# ---------------------------------------------------------------- what only the tests and benchmarks need

# pyproject.toml's `test` and `bench` extras: the package's own code imports none of them, but the reference UKF the
# tests and the benches compare with, which is the package's module for them to share
TEST_ONLY = ("filterpy", "webdataset")
TEST_ONLY_HOMES = (os.path.join("filtering", "reference.py"),)


def imports_of_test_extras(root: str = ROOT) -> list[str]:
    """'file:line imports name' for each import of a test-only library by the package's code (homes apart)."""
    found = []
    for path, module in source_files(root):
        rel = os.path.relpath(path, root)
        if rel in TEST_ONLY_HOMES:
            continue
        found += [f"{rel}:{line} imports {name}" for line, name in imported_modules(path, module)
                  if name.split(".")[0] in TEST_ONLY]
    return found


# ---------------------------------------------------------------- one home for each concept

STATE_FILE = os.path.join("envisat_pose", "state.py")
GATES_FILE = os.path.join("envisat_pose", "gates.py")
ONBOARD_FILE = os.path.join("pipelines", "tracking", "onboard.py")
RESUMABLE_FILE = os.path.join("envisat_pose", "resumable.py")  # the manifest protocol (ResumableJob)
SHARD_READER_FILE = os.path.join("envisat_pose", "shard_reader.py")
WEIGHTS_KEYS_FILE = os.path.join("perception", "weights_keys.py")  # the weights' metadata keys
POOLS_FILE = os.path.join("envisat_pose", "pools.py")  # the machine's usable cores (usable_cores)
IO_FILE = os.path.join("envisat_pose", "io.py")  # the one .npz reader (open_npz)
CORE_COUNTERS = ("cpu_count", "sched_getaffinity", "process_cpu_count")  # os's and multiprocessing's
METADATA_CALLS = ("with_metadata", "save_weights", "save_adapted", "read_metadata", "read_header")
METADATA_NAMES = ("meta", "metadata")  # the names a weights file's metadata dict goes by
STATE_BOUNDS = {(0, 3), (3, 6), (6, 9), (9, 12)}  # the blocks of the 12-state (envisat_pose.state)
MERGERS = ("set_dotted", "deep_update")  # the layers of a config, merged by hand


def _called_name(node: ast.Call) -> str | None:
    f = node.func
    return f.id if isinstance(f, ast.Name) else f.attr if isinstance(f, ast.Attribute) else None


def _int_const(node) -> int | None:
    return node.value if isinstance(node, ast.Constant) and type(node.value) is int else None


def state_slice_definitions(source: str) -> list[int]:
    """Lines that build one of the state's block slices: slice(6, 9) and friends, or np.s_[6:9]. A comparison
    with the core's slices (a guard that code written for the layout still matches it) is no definition."""
    tree = parse(source)
    compared = {id(n) for c in walk(tree) if isinstance(c, ast.Compare) for n in walk(c)}
    lines = []
    for node in walk(tree):
        if id(node) in compared:
            continue
        bounds = None
        if isinstance(node, ast.Call) and _called_name(node) == "slice" and len(node.args) == 2:
            bounds = tuple(_int_const(a) for a in node.args)
        elif (isinstance(node, ast.Subscript) and isinstance(node.slice, ast.Slice)
              and isinstance(node.value, (ast.Name, ast.Attribute))
              and (node.value.id if isinstance(node.value, ast.Name) else node.value.attr) in ("s_", "index_exp")):
            bounds = (_int_const(node.slice.lower), _int_const(node.slice.upper))
        if bounds in STATE_BOUNDS:
            lines.append(node.lineno)
    return sorted(lines)


def _mentions(node: ast.AST, names: set[str]) -> bool:
    return any((isinstance(n, ast.Constant) and n.value == "manifest.json") or (isinstance(n, ast.Name) and n.id in names)
               for n in walk(node))


def manifest_writes(source: str) -> list[int]:
    """Lines that write a file named manifest.json (directly, or through names bound to it): a manifest
    protocol of its own. Reading one (a dataset's, to check it) is fine."""
    tree = parse(source)
    tainted: set[str] = set()  # names bound to the manifest's name or path
    while True:
        more = {t.id for n in walk(tree) if isinstance(n, (ast.Assign, ast.AnnAssign)) and n.value is not None
                and _mentions(n.value, tainted)
                for t in (n.targets if isinstance(n, ast.Assign) else [n.target]) if isinstance(t, ast.Name)}
        if more <= tainted:
            break
        tainted |= more
    lines = []
    for n in walk(tree):
        if not isinstance(n, ast.Call):
            continue
        name, target = _called_name(n), None
        if name in ("atomic_write_text", "atomic_path") and n.args:
            target = n.args[0]
        elif name == "open" and n.args:
            mode = n.args[1] if len(n.args) > 1 else next((k.value for k in n.keywords if k.arg == "mode"), None)
            if isinstance(mode, ast.Constant) and isinstance(mode.value, str) and set(mode.value) & set("wax"):
                target = n.args[0]
        elif name in ("write_text", "write_bytes") and isinstance(n.func, ast.Attribute):
            target = n.func.value
        if target is not None and _mentions(target, tainted):
            lines.append(n.lineno)
    return sorted(lines)


def tar_reads(source: str) -> list[int]:
    """Lines that open a tar for reading (tarfile.open without a mode, or with one starting 'r'; a WebDataset
    or TarFile built directly): a shard reader of its own. Writing a tar is fine."""
    lines = []
    for n in walk(parse(source)):
        if not isinstance(n, ast.Call):
            continue
        name = _called_name(n)
        if name in ("WebDataset", "TarFile"):
            lines.append(n.lineno)
        elif name == "open" and isinstance(n.func, ast.Attribute) and isinstance(n.func.value, ast.Name) \
                and n.func.value.id == "tarfile":
            mode = n.args[1] if len(n.args) > 1 else next((k.value for k in n.keywords if k.arg == "mode"), None)
            if mode is None or (isinstance(mode, ast.Constant) and str(mode.value).startswith("r")):
                lines.append(n.lineno)
    return sorted(lines)


@functools.cache
def weights_key_values() -> frozenset[str]:
    """The metadata keys perception/weights_keys.py names (its string constants)."""
    tree = parse(open(os.path.join(ROOT, WEIGHTS_KEYS_FILE), encoding="utf-8").read())
    return frozenset(n.value.value for n in tree.body if isinstance(n, ast.Assign)
                     and isinstance(n.value, ast.Constant) and isinstance(n.value.value, str))


def _is_metadata(node) -> bool:
    """A weights file's metadata: a read_metadata / read_header call's result or a variable named so."""
    return (isinstance(node, ast.Call) and _called_name(node) in METADATA_CALLS) \
        or (isinstance(node, ast.Name) and node.id in METADATA_NAMES)


def typed_weights_keys(source: str, keys: frozenset[str] | None = None) -> list[int]:
    """Lines that type a weights file's metadata key as a string (perception/weights_keys.py names each): a key of
    a dict literal given to a metadata writer or merged into the metadata, or a key looked up in the metadata
    (meta[k], meta.get(k), k in meta)."""
    keys = weights_key_values() if keys is None else keys

    def typed(node) -> bool:
        return isinstance(node, ast.Constant) and node.value in keys

    lines = []
    for n in walk(parse(source)):
        dicts = []
        if isinstance(n, ast.Call) and (_called_name(n) in METADATA_CALLS or (
                _called_name(n) == "update" and isinstance(n.func, ast.Attribute) and _is_metadata(n.func.value))):
            dicts = [a for a in list(n.args) + [k.value for k in n.keywords] if isinstance(a, ast.Dict)]
        if isinstance(n, ast.Assign) and any(_is_metadata(t) for t in n.targets) and isinstance(n.value, ast.Dict):
            dicts = [n.value]
        if any(typed(k) for d in dicts for k in d.keys):
            lines.append(n.lineno)
        elif isinstance(n, ast.Subscript) and _is_metadata(n.value) and typed(n.slice):
            lines.append(n.lineno)
        elif isinstance(n, ast.Call) and _called_name(n) == "get" and isinstance(n.func, ast.Attribute) \
                and _is_metadata(n.func.value) and n.args and typed(n.args[0]):
            lines.append(n.lineno)
        elif isinstance(n, ast.Compare) and typed(n.left) and any(_is_metadata(c) for c in n.comparators):
            lines.append(n.lineno)
    return sorted(set(lines))


def hand_resolutions(source: str) -> list[int]:
    """Lines of functions that resolve a config by hand: merging layers (set_dotted, deep_update), or reading a
    TOML file and building a config from it (load_toml with from_dict) in one function."""
    lines = []
    for fn in walk(parse(source)):
        if not isinstance(fn, (ast.FunctionDef, ast.AsyncFunctionDef)):
            continue
        calls = [n for n in walk(fn) if isinstance(n, ast.Call)]
        names = {_called_name(c) for c in calls}
        if names & set(MERGERS) or {"load_toml", "from_dict"} <= names:
            lines.append(fn.lineno)
    return sorted(set(lines))


def run_configs_built(source: str) -> list[int]:
    """Lines where a RunConfig is built straight from a dict (from_dict(RunConfig, ...)) instead of through
    config.resolve_job_config (app.run.run_config for a scenario's run): the tests' and benchmarks' copies of the
    app's resolution that issue 29 found."""
    lines = []
    for node in walk(parse(source)):
        if isinstance(node, ast.Call) and _called_name(node) == "from_dict" and node.args:
            a = node.args[0]
            name = a.attr if isinstance(a, ast.Attribute) else getattr(a, "id", "")
            if name == "RunConfig":
                lines.append(node.lineno)
    return sorted(lines)


def _chi2_values() -> list[float]:
    """Chi-square bounds a gate typed by hand would hold: 1 to 4 dof, tail probabilities 0.05 to 1e-7."""
    from scipy.stats import chi2

    tails = (0.05, 0.01, 0.0027, 1e-3, 1e-4, 1e-5, 1e-6, 1e-7)
    return [float(chi2.isf(q, d)) for q in tails for d in (1, 2, 3, 4)]


def _near_chi2(node, table) -> bool:
    v = node.value if isinstance(node, ast.Constant) and type(node.value) in (int, float) else None
    return v is not None and v > 1.0 and min(abs(v - b) / b for b in table) < 0.005


def _speaks_of_gate(text: str) -> bool:
    """Whether a name in the text is a gate's and carries no unit (a chi-square gate is a pure number; a
    distance gate like gate_px is not one)."""
    return any("gate" in n.lower() and not re.search(r"_(px|px2|m|s|deg|rad)$", n)
               for n in re.findall(r"[A-Za-z_][A-Za-z0-9_]*", text))


def core_counts(source: str) -> list[int]:
    """Lines that count the machine's cores by hand (os.cpu_count(), os.sched_getaffinity(), a bare cpu_count()):
    the package's defaults take envisat_pose.pools.usable_cores."""
    return sorted({node.lineno for node in walk(parse(source)) if isinstance(node, ast.Call)
                   and (getattr(node.func, "attr", None) or getattr(node.func, "id", None)) in CORE_COUNTERS})


def npz_loads(source: str) -> list[int]:
    """Lines that open an .npz with numpy's load (np.load, numpy.load, a bare load imported from numpy): the
    package reads every .npz through envisat_pose.io.open_npz, which closes its file on every way out and names a
    file that is not an .npz (np.load keeps its file open where a zip is damaged, reads an .npy as one array)."""
    numpy_names = {"np", "numpy"}
    bare = set()
    for node in walk(parse(source)):
        if isinstance(node, ast.ImportFrom) and node.module == "numpy":
            bare |= {a.asname or a.name for a in node.names if a.name == "load"}
    return sorted({node.lineno for node in walk(parse(source)) if isinstance(node, ast.Call) and (
        (isinstance(node.func, ast.Attribute) and node.func.attr == "load"
         and isinstance(node.func.value, ast.Name) and node.func.value.id in numpy_names)
        or (isinstance(node.func, ast.Name) and node.func.id in bare))})


def typed_gates(source: str) -> list[int]:
    """Lines where a chi-square gate is typed as a number (within 0.5 % of a chi-square bound of 1-4 dof at a
    usual tail probability) in a statement that speaks of a gate: a parameter or field named *gate*, or any
    simple statement (an `if`'s or `while`'s test) whose text names one (names with a unit, like gate_px, are
    distances, not chi-square gates). The gate comes from its probability
    (envisat_pose.gates.chi2_gate)."""
    table = _chi2_values()
    lines = []
    for node in walk(parse(source)):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)):
            a = node.args
            pos = a.posonlyargs + a.args
            pairs = list(zip(pos[len(pos) - len(a.defaults):], a.defaults))
            pairs += [(k, d) for k, d in zip(a.kwonlyargs, a.kw_defaults) if d is not None]
            lines += [d.lineno for arg, d in pairs if _speaks_of_gate(arg.arg) and _near_chi2(d, table)]
            continue
        if isinstance(node, (ast.If, ast.While)):
            part = node.test
        elif isinstance(node, ast.stmt) and not hasattr(node, "body"):
            part = node
        else:
            continue
        if _speaks_of_gate(ast.unparse(part)):
            lines += [c.lineno for c in walk(part) if _near_chi2(c, table)]
    return sorted(set(lines))


@functools.cache
def _chi2_band_values() -> tuple[float, ...]:
    """Chi-square quantiles a band typed by hand would hold: 1 to 36 dof, the usual one- and two-sided levels."""
    from scipy.stats import chi2

    levels = (0.001, 0.005, 0.01, 0.025, 0.05, 0.95, 0.975, 0.99, 0.995, 0.999)
    return tuple(float(chi2.ppf(p, d)) for p in levels for d in range(1, 37))


def _typed_quantile(node, table) -> bool:
    """A float literal of 3 or more significant digits within 0.2 % of a table value (a round 8.0 or 16.0 is a
    floor someone chose, not a quantile copied from a table)."""
    if not (isinstance(node, ast.Constant) and type(node.value) is float and node.value > 0.0):
        return False
    digits = repr(node.value).split("e")[0].replace(".", "").strip("0")
    return len(digits) >= 3 and min(abs(node.value - b) / b for b in table) < 0.002


def typed_bands(source: str) -> list[int]:
    """Lines where a chi-square band (of NEES, NIS, a consistency test) is typed as numbers: a float literal
    within 0.2 % of a chi-square quantile (1-36 dof) in a simple statement (an `if`'s or `while`'s test) whose
    text names a band, NEES, NIS or chi-square. The band comes from scipy.stats.chi2 (analysis.stats'
    chi2_mean_bounds, envisat_pose.gates)."""
    table = _chi2_band_values()
    lines = []
    for node in walk(parse(source)):
        if isinstance(node, (ast.If, ast.While)):
            part = node.test
        elif isinstance(node, ast.stmt) and not hasattr(node, "body"):
            part = node
        else:
            continue
        if re.search(r"band|nees|nis|chi", ast.unparse(part), re.IGNORECASE):
            lines += [c.lineno for c in walk(part) if _typed_quantile(c, table)]
    return sorted(set(lines))


def app_imports(path: str, source: str | None = None) -> list[int]:
    """Lines where a file outside the package (a bench, a script) imports a verb module (envisat_pose.app.*) or
    a stage by its old top-level name."""
    return sorted({line for line, name in imported_modules(path, "outside", source)
                   if (layer_of(name) or "") == "app" or (layer_of(name) or "").startswith("bare:")})


def _access(node) -> tuple[str, ast.AST] | None:
    """(name, container) of `container.name` or `container["name"]`."""
    if isinstance(node, ast.Attribute):
        return node.attr, node.value
    if isinstance(node, ast.Subscript) and isinstance(node.slice, ast.Constant) and isinstance(node.slice.value, str):
        return node.slice.value, node.value
    return None


def physics_builders(source: str) -> list[int]:
    """Lines of functions that read the truth's physics for the filter by hand: orbit.mu_m3_s2 together with
    target.gravity_gradient (as attributes or keys) of one config. One builder: pipelines/tracking/onboard.py's
    onboard_physics."""
    lines = []
    for fn in walk(parse(source)):
        if not isinstance(fn, (ast.FunctionDef, ast.AsyncFunctionDef)):
            continue
        seen = set()
        for n in walk(fn):
            a = _access(n)
            if a is not None and a[0] in ("mu_m3_s2", "gravity_gradient"):
                inner = _access(a[1])
                if inner is not None and (a[0], inner[0]) in (("mu_m3_s2", "orbit"), ("gravity_gradient", "target")):
                    seen.add(a[0])
        if len(seen) == 2:
            lines.append(fn.lineno)
    return sorted(lines)


def filter_side(rel: str) -> bool:
    """Whether a file is on the filter's side of the truth (a pipeline, a verb, a bench or a test helper): the
    truth's own physics (datagen) reads its config freely."""
    parts = rel.split(os.sep)
    return (len(parts) > 1 and parts[0] in UPPER) or parts[0] in ("bench", "scripts", "tests")


def resolves_configs(rel: str) -> bool:
    """Whether a file is a verb or a pipeline (the layers that resolve job configs)."""
    parts = rel.split(os.sep)
    return len(parts) > 1 and parts[0] in UPPER


def copies(kind: str, root: str = ROOT) -> dict[str, list[int]]:
    """{file: lines} of every copy of one kind in the repository (pending ones included)."""
    found = {}
    for rel in checked_files(root, EXTRA_FOLDERS + (("tests",) if kind in WITH_TESTS else ())):
        source = open(os.path.join(root, rel), encoding="utf-8").read()
        if kind == "state_slices" and rel != STATE_FILE:
            lines = state_slice_definitions(source)
        elif kind == "manifest_writers" and rel != RESUMABLE_FILE:
            lines = manifest_writes(source)
        elif kind == "hand_built_runs" and rel.split(os.sep)[0] in ("tests", "bench", "scripts") and rel != THIS_FILE:
            lines = run_configs_built(source)
        elif kind == "hand_resolved_configs" and resolves_configs(rel):
            lines = hand_resolutions(source)
        elif kind == "physics_builders" and rel != ONBOARD_FILE and filter_side(rel):
            lines = physics_builders(source)
        elif kind == "typed_gates" and rel != GATES_FILE:
            lines = typed_gates(source)
        elif kind == "shard_readers" and rel != SHARD_READER_FILE:
            lines = tar_reads(source)
        elif kind == "typed_bands":
            lines = typed_bands(source)
        elif kind == "typed_weights_keys" and rel != WEIGHTS_KEYS_FILE:
            lines = typed_weights_keys(source)
        elif kind == "machine_counts" and rel != POOLS_FILE and rel.split(os.sep)[0] not in EXTRA_FOLDERS:
            lines = core_counts(source)
        elif kind == "npz_readers" and rel != IO_FILE and rel.split(os.sep)[0] not in EXTRA_FOLDERS:
            lines = npz_loads(source)
        elif kind == "app_imports" and rel.split(os.sep)[0] in EXTRA_FOLDERS:
            lines = app_imports(rel, source)
        else:
            lines = []
        if lines:
            found[rel] = lines
    return found


# ---------------------------------------------------------------- the tests

def test_layers_follow_the_import_rule():
    assert violations() == []


def test_the_checker_sees_a_crossing(tmp_path):
    """The rule test can fail: a stage importing another stage (inside a function) is reported."""
    bad = tmp_path / "filtering"
    bad.mkdir()
    (bad / "x.py").write_text("def f():\n    from envisat_pose.datagen.truth import simulate\n    from ..analysis import plots\n")
    found = []
    for line, name in imported_modules(str(bad / "x.py"), "envisat_pose.filtering.x"):
        if layer_of(name) not in (None, "core", "filtering"):
            found.append(name)
    assert "envisat_pose.datagen.truth" in found and "envisat_pose.analysis" in found


@pytest.mark.parametrize("module, source, reason", [
    ("envisat_pose.filtering.x", "from envisat_pose.pipelines.runs import track\n", "a stage imports only the core"),
    ("envisat_pose.state", "def f():\n    from envisat_pose.pipelines.runs.track import x\n", "nothing above it"),
    ("envisat_pose.pipelines.x", "from envisat_pose.app.cli import main\n", "never the app"),
])
def test_pipelines_layer_crossings_are_seen(module, source, reason):
    why = [crossing(layer_of(module), layer_of(name)) for _, name in imported_modules("x.py", module, source)]
    assert any(w and reason in w for w in why), why


def test_pipelines_may_import_core_and_stages_and_the_app_anything():
    src = "from envisat_pose.filtering import estimator\nfrom envisat_pose.datagen import render\nimport envisat_pose.state\n"
    for name in (n for _, n in imported_modules("x.py", "envisat_pose.pipelines.x", src)):
        assert crossing("pipelines", layer_of(name)) is None, name
    assert crossing("app", "pipelines") is None


def test_no_import_cycles():
    """Modules that import one another, even through an import inside a function (which hides the cycle from
    Python until the call), are one module's job in two files: move the shared piece down (floor: 0 cycles)."""
    assert import_cycles(module_graph()) == []


def test_the_cycle_checker_sees_a_cycle_hidden_in_a_function(tmp_path):
    (tmp_path / "pipelines").mkdir()
    (tmp_path / "pipelines" / "a.py").write_text("from envisat_pose.pipelines.b import x\n")
    (tmp_path / "pipelines" / "b.py").write_text("def x():\n    from envisat_pose.pipelines import c\n")
    (tmp_path / "pipelines" / "c.py").write_text("def y():\n    from .a import z\n")
    (tmp_path / "pipelines" / "d.py").write_text("from envisat_pose.pipelines.a import z\n")  # imports, not in one
    graph = module_graph(str(tmp_path))
    assert graph["envisat_pose.pipelines.c"] == {"envisat_pose.pipelines.a"}
    assert import_cycles(graph) == [["envisat_pose.pipelines.a", "envisat_pose.pipelines.b", "envisat_pose.pipelines.c"]]
    assert import_cycles({"a": {"b"}, "b": set(), "c": {"a", "b"}}) == []


# ---------------------------------------------------------------- one Target: only it asks whether it is ENVISAT

TARGET_FILE = os.path.join("envisat_pose", "target.py")
DEFAULT_QUESTIONS = frozenset({"is_default", "is_envisat"})  # the Target's own answer, and the old one's name
DEFAULT_NAMES = frozenset({"DEFAULT_TARGET", "ENVISAT_TARGET"})
DEFAULT_STRINGS = frozenset({"envisat", "models/envisat.xml", "ENVISAT"})


def _is_default_operand(node) -> bool:
    if isinstance(node, ast.Constant) and node.value in DEFAULT_STRINGS:
        return True
    if isinstance(node, ast.Name | ast.Attribute):
        return (node.id if isinstance(node, ast.Name) else node.attr) in DEFAULT_NAMES
    return isinstance(node, ast.Call) and _called_name(node) == "model_path"


def default_target_questions(source: str) -> list[int]:
    """Lines that ask whether the target is ENVISAT: `.is_default` / `.is_envisat`, or a comparison (==, !=, in,
    is) with the default target's name, file or path (DEFAULT_TARGET, "envisat", "models/envisat.xml",
    model_path())."""
    lines = []
    for node in walk(parse(source)):
        if isinstance(node, ast.Attribute) and node.attr in DEFAULT_QUESTIONS:
            lines.append(node.lineno)
        elif isinstance(node, ast.Compare) and any(_is_default_operand(n) for n in [node.left, *node.comparators]):
            lines.append(node.lineno)
    return sorted(set(lines))


def test_only_the_target_asks_whether_it_is_envisat():
    """Every layer takes a Target and asks it what it is made of (its keypoints, geoms, own_scene,
    labels_name_keypoints...); whether it is ENVISAT is asked in envisat_pose/target.py alone (floor: 0 lines
    elsewhere in the package)."""
    found = [f"{os.path.relpath(path, ROOT)}:{line}" for path, _ in source_files()
             if os.path.relpath(path, ROOT) != TARGET_FILE
             for line in default_target_questions(open(path, encoding="utf-8").read())]
    assert found == [], f"asks whether the target is ENVISAT outside {TARGET_FILE}: {found}"


def test_the_default_question_checker_sees_each_form():
    planted = ("def f(t, cfg, m):\n    a = t.is_default\n    b = cfg.target == DEFAULT_TARGET\n"
               "    c = m.name != 'envisat'\n    d = path == model_path()\n    e = cfg.target\n")
    assert default_target_questions(planted) == [2, 3, 4, 5]


# ---------------------------------------------------------------- pipelines/ grouped by job

# The sub-packages of pipelines/, one per job, and the modules allowed at its root: jobs.py resolves a named scenario
# into any job's config, so it sits above every group (no group imports it).
PIPELINE_GROUPS = ("common", "tracking", "runs", "campaigns", "detector", "adaptation", "datasets")
PIPELINE_ROOT_MODULES = ("envisat_pose.pipelines", "envisat_pose.pipelines.jobs")


def pipeline_group(module: str, packages: set[str]) -> str | None:
    """The group of a pipelines module ('root' for the package and its root modules), None outside pipelines/.
    packages: the modules that are packages (a group's own __init__ belongs to the group)."""
    parts = module.split(".")
    if parts[:2] != ["envisat_pose", "pipelines"] or len(parts) < 3 and module != "envisat_pose.pipelines":
        return None
    return parts[2] if len(parts) > 3 or module in packages else "root"


def pipeline_groups_problems(graph: dict[str, set[str]]) -> list[str]:
    """What breaks the grouping: a module at pipelines/'s root besides PIPELINE_ROOT_MODULES or in an unknown
    group, a group that imports the root, and the cycles of the groups' import graph (a group's edge to another
    stands for every import between their modules)."""
    found = []
    groups: dict[str, set[str]] = {}
    packages = {m.rsplit(".", 1)[0] for m in graph if m.count(".") > 2}
    for module, deps in graph.items():
        own = pipeline_group(module, packages)
        if own is None:
            continue
        if own == "root" and module not in PIPELINE_ROOT_MODULES and module.count(".") == 2:
            found.append(f"{module} lies at pipelines/'s root: move it into the group of its job")
        elif own != "root" and own not in PIPELINE_GROUPS:
            found.append(f"{module} is in an unknown group {own!r} (PIPELINE_GROUPS lists them)")
        for dep in deps:
            other = pipeline_group(dep, packages)
            if other is None or other == own:
                continue
            if other == "root" and own != "root":
                found.append(f"{module} imports {dep}: a group never imports pipelines/'s root")
            groups.setdefault(own, set()).add(other)
    found += [f"the groups {' and '.join(c)} import one another" for c in import_cycles(
        {g: groups.get(g, set()) for g in set(groups) | {d for ds in groups.values() for d in ds}})]
    return found


def test_pipelines_are_grouped_by_job_without_loops():
    """Every pipeline lives in the group of its job (pipelines/<group>/); the groups import one another without a
    loop and never the root (floor: 0 problems)."""
    assert pipeline_groups_problems(module_graph()) == []


def test_the_group_checker_sees_a_loop_a_stray_and_an_import_of_the_root(tmp_path):
    for group in ("runs", "tracking"):
        (tmp_path / "pipelines" / group).mkdir(parents=True)
        (tmp_path / "pipelines" / group / "__init__.py").write_text("")
    (tmp_path / "pipelines" / "jobs.py").write_text("from envisat_pose.pipelines.runs import track\n")
    (tmp_path / "pipelines" / "stray.py").write_text("")
    (tmp_path / "pipelines" / "runs" / "track.py").write_text("from envisat_pose.pipelines.tracking.tracker import T\n")
    (tmp_path / "pipelines" / "tracking" / "tracker.py").write_text(
        "def f():\n    from envisat_pose.pipelines.runs.rows import x\n")
    (tmp_path / "pipelines" / "runs" / "rows.py").write_text("from envisat_pose.pipelines import jobs\n")
    assert sorted(pipeline_groups_problems(module_graph(str(tmp_path)))) == [
        "envisat_pose.pipelines.runs.rows imports envisat_pose.pipelines.jobs: a group never imports pipelines/'s root",
        "envisat_pose.pipelines.stray lies at pipelines/'s root: move it into the group of its job",
        "the groups root and runs and tracking import one another"]  # rows -> jobs -> runs too


def test_one_name_per_concept():
    """No two modules define the same public name (floor: 0 besides PENDING_COLLISIONS, which only shrinks):
    a reader who meets `FrameSource` must know which one it is without reading the import."""
    found = {n: w for n, w in collisions().items() if n not in PENDING_COLLISIONS}
    assert found == {}, f"public names defined twice: {found}; name each for what it is"


def test_pending_collisions_are_still_there():
    """A pending entry whose name no longer collides is stale: delete it from PENDING_COLLISIONS."""
    stale = sorted(PENDING_COLLISIONS - set(collisions()))
    assert stale == [], f"{stale} no longer collide; remove them from PENDING_COLLISIONS"


def test_the_name_checker_sees_a_planted_twin(tmp_path):
    for folder in ("pipelines", "app"):
        (tmp_path / folder).mkdir()
    (tmp_path / "pipelines" / "frames.py").write_text("class FrameSource:\n    pass\n\ndef _helper():\n    pass\n")
    (tmp_path / "pipelines" / "online.py").write_text("class FrameSource:\n    pass\n\ndef _helper():\n    pass\n")
    (tmp_path / "pipelines" / "labels.py").write_text("X = 1\n")
    (tmp_path / "pipelines" / "adapt.py").write_text("def labels(run):\n    return run\n")
    (tmp_path / "app" / "a.py").write_text("def register(sub):\n    pass\n")
    (tmp_path / "app" / "b.py").write_text("def register(sub):\n    pass\n")
    assert collisions(str(tmp_path)) == {
        "FrameSource": ["envisat_pose.pipelines.frames", "envisat_pose.pipelines.online"],
        "module:labels": ["envisat_pose.pipelines.adapt", "envisat_pose.pipelines.labels"]}


def test_the_package_does_not_need_the_test_extras():
    """filterpy and webdataset are extras for the tests and the benchmarks (pyproject.toml), not dependencies:
    no runtime module imports them, and the extras list them."""
    import tomllib

    assert imports_of_test_extras() == []
    with open(os.path.join(ROOT, "pyproject.toml"), "rb") as fh:
        project = tomllib.load(fh)["project"]
    deps = " ".join(project["dependencies"])
    extras = " ".join(project["optional-dependencies"]["test"] + project["optional-dependencies"]["bench"])
    assert [n for n in TEST_ONLY if n in deps] == [] and all(n in extras for n in TEST_ONLY)


def test_the_test_only_checker_sees_a_runtime_import(tmp_path):
    (tmp_path / "filtering").mkdir()
    (tmp_path / "filtering" / "x.py").write_text("def f():\n    from filterpy.kalman import UnscentedKalmanFilter\n")
    (tmp_path / "filtering" / "reference.py").write_text("import filterpy\n")
    assert imports_of_test_extras(str(tmp_path)) == [f"{os.path.join('filtering', 'x.py')}:2 imports filterpy.kalman",
                                                f"{os.path.join('filtering', 'x.py')}:2 imports "
                                                "filterpy.kalman.UnscentedKalmanFilter"]


def test_every_stage_file_is_seen():
    mods = {m for _, m in source_files()}
    for stage in STAGES:
        assert f"envisat_pose.{stage}" in mods
    assert "envisat_pose.app.cli" in mods and "envisat_pose.contracts" in mods and "envisat_pose.state" in mods
    assert "envisat_pose.pipelines" in mods and "envisat_pose.pipelines.tracking.tracker" in mods


def test_a_missing_layer_folder_is_walked_without_error(tmp_path):
    (tmp_path / "envisat_pose").mkdir()
    (tmp_path / "app").mkdir()
    (tmp_path / "envisat_pose" / "state.py").write_text("")
    (tmp_path / "app" / "cli.py").write_text("")
    mods = {m for _, m in source_files(str(tmp_path))}
    assert mods == {"envisat_pose.state", "envisat_pose.app.cli"}


def test_each_layer_is_a_folder_at_the_root_installed_inside_envisat_pose():
    """The repository's own picture: envisat_pose/ holds the core alone, every other layer is a folder beside
    it (inside envisat_pose/ only as a link to it, for editors: tests/test_editor_layout.py), and the package's
    build maps each folder into envisat_pose."""
    import tomllib

    core = os.path.join(ROOT, "envisat_pose")
    assert not [d for d in os.listdir(core) if os.path.isfile(os.path.join(core, d, "__init__.py"))
                and not os.path.islink(os.path.join(core, d))]
    with open(os.path.join(ROOT, "pyproject.toml"), "rb") as fh:
        package_dir = tomllib.load(fh)["tool"]["setuptools"]["package-dir"]
    for folder, package in LAYOUT.items():
        if folder != "envisat_pose":
            assert package_dir.get(package) == folder, package
            assert os.path.isfile(os.path.join(ROOT, folder, "__init__.py")), folder


@functools.lru_cache(maxsize=None)
def repository_copies(kind: str) -> dict[str, list[int]]:
    """copies(kind) of this repository, found once for the two tests that read them (not to be changed)."""
    return copies(kind)


@pytest.mark.parametrize("kind", sorted(PENDING))
def test_one_home_for_each_concept(kind):
    found = {f: lines for f, lines in repository_copies(kind).items() if f not in PENDING[kind]}
    assert found == {}, f"{kind}: second copies at {found} (one home: see this file's docstring)"


@pytest.mark.parametrize("kind", sorted(PENDING))
def test_pending_copies_are_still_there(kind):
    """A pending entry whose copy is gone is stale: delete it from PENDING."""
    found = repository_copies(kind)
    stale = [f for f in PENDING[kind] if f not in found]
    assert stale == [], f"{kind}: {stale} no longer hold a copy; remove them from PENDING"


def test_the_weights_key_checker_sees_each_form():
    keys = frozenset({"cov_scale", "error_model"})
    planted = ("meta = read_metadata(p)\n"
               "x = meta['cov_scale']\n"
               "y = read_metadata(p).get('error_model')\n"
               "with_metadata(p, q, {'cov_scale': 2.0})\n"
               "meta.update({'error_model': s})\n"
               "z = 'cov_scale' in meta\n"
               "meta = {'format': F, 'cov_scale': 1}\n"
               "ok = {'cov_scale': det.cfg.cov_scale}\n"
               "ok = res['error_model']\n"
               "with_metadata(p, q, {COV_SCALE_KEY: 2.0})\n")
    assert typed_weights_keys(planted, keys) == [2, 3, 4, 5, 6, 7]
    assert {"cov_scale", "error_model", "keypoint_sigma_px"} <= weights_key_values()


def test_the_core_count_checker_sees_each_way_to_count():
    planted = ("import os, multiprocessing\nfrom os import cpu_count\n"
               "a = os.cpu_count() or 1\n"
               "b = len(os.sched_getaffinity(0))\n"
               "c = multiprocessing.cpu_count()\n"
               "d = cpu_count()\n"
               "from envisat_pose.pools import usable_cores\ne = usable_cores()\n")
    assert core_counts(planted) == [3, 4, 5, 6]
    assert core_counts(open(os.path.join(ROOT, POOLS_FILE), encoding="utf-8").read())  # the home


def test_the_npz_reader_checker_sees_each_way_to_load():
    planted = ("import numpy as np\nimport numpy\nfrom numpy import load as npload\n"
               "a = np.load(p)\n"
               "with numpy.load(p, allow_pickle=False) as z:\n    pass\n"
               "c = npload(p)\n"
               "d = torch.load(p, weights_only=True)\ne = json.load(fh)\nf = open_npz(p)\n")
    assert npz_loads(planted) == [4, 5, 7]
    assert npz_loads(open(os.path.join(ROOT, IO_FILE), encoding="utf-8").read())  # the home


def test_the_state_slice_checker_catches_a_planted_copy():
    planted = ("import numpy as np\nMRP = slice(6, 9)\nBLOCKS = (slice(0, 3), slice(3, 6))\n"
               "RATE = np.s_[9:12]\nCROP = slice(0, 5)\n")
    assert state_slice_definitions(planted) == [2, 3, 3, 4]
    assert state_slice_definitions("from envisat_pose.state import MRP\ny = x[..., MRP]\n") == []
    guard = "from envisat_pose.state import MRP\nif MRP != slice(6, 9):\n    raise ImportError('layout changed')\n"
    assert state_slice_definitions(guard) == []
    assert state_slice_definitions(open(os.path.join(ROOT, STATE_FILE), encoding="utf-8").read())  # the home


def test_the_manifest_checker_catches_a_planted_protocol():
    planted = ("import json, os\nfrom envisat_pose.io import atomic_write_text, sha256_file\n\n"
               "def record(out_dir, done):\n"
               "    atomic_write_text(os.path.join(out_dir, 'manifest.json'), json.dumps(done))\n")
    assert manifest_writes(planted) == [5]
    indirect = ("import json, os\nMANIFEST = 'manifest.json'\n\ndef record(out_dir, done):\n"
                "    path = os.path.join(out_dir, MANIFEST)\n"
                "    with open(path, 'w') as fh:\n        json.dump(done, fh)\n")
    assert manifest_writes(indirect) == [6]
    reader = ("import json\n\ndef read(d):\n    m = json.load(open(d + '/manifest.json'))\n"
              "    open(d + '/summary.json', 'w').write(json.dumps(m))\n")
    assert manifest_writes(reader) == []
    assert manifest_writes(open(os.path.join(ROOT, RESUMABLE_FILE), encoding="utf-8").read())  # the home


def test_the_shard_reader_checker_catches_a_planted_reader():
    planted = ("import tarfile\nimport webdataset as wds\n\n"
               "def poses(path):\n    with tarfile.open(path) as tar:\n        return list(tar)\n\n"
               "def more(path):\n    return tarfile.open(path, mode='r:*'), wds.WebDataset([path])\n")
    assert tar_reads(planted) == [5, 9, 9]
    writer = "import tarfile\n\ndef write(path):\n    return tarfile.open(path, 'w', format=tarfile.USTAR_FORMAT)\n"
    assert tar_reads(writer) == []
    assert tar_reads(open(os.path.join(ROOT, SHARD_READER_FILE), encoding="utf-8").read())  # the home


def test_the_config_checker_catches_a_verb_resolving_by_hand():
    by_hand = ("from envisat_pose.config import deep_update, from_dict, load_toml, set_dotted\n\n"
               "def resolve_config(args):\n"
               "    data = deep_update({}, load_toml(args.config))\n"
               "    data = set_dotted(data, 'seed', args.seed)\n"
               "    return from_dict(Cfg, data)\n\n"
               "def from_file(path):\n"
               "    return from_dict(Cfg, load_toml(path))\n")
    assert hand_resolutions(by_hand) == [3, 8]
    resolved = ("from envisat_pose.config import load_toml, resolve_job_config\n\n"
                "def resolve_config(args):\n"
                "    return resolve_job_config(Cfg, {}, args.config, {'seed': args.seed})\n\n"
                "def camera(path):\n"
                "    return load_toml(path)['fx']\n")
    assert hand_resolutions(resolved) == []
    assert resolves_configs(os.path.join("app", "run.py"))
    assert resolves_configs(os.path.join("pipelines", "runs", "track.py"))
    assert not resolves_configs(os.path.join("envisat_pose", "config.py"))
    assert not resolves_configs(os.path.join("envisat_pose", "config_layers.py"))


def test_the_gate_checker_catches_a_gate_typed_by_hand():
    planted = ("from dataclasses import dataclass\n\n@dataclass\nclass Cfg:\n    fit_gate: float = 23.0\n\n"
               "def fit(z, gate: float = 23.0, iterations: int = 15):\n    return z\n\n"
               "def step(setup, d2):\n    thr = setup.gate_threshold if setup.gate_threshold is not None else 23.0\n"
               "    if d2 > 25.9 and setup.gated:\n        return thr\n")
    assert typed_gates(planted) == [5, 7, 11, 12]
    derived = ("from envisat_pose.gates import GATE_PROB, chi2_gate\n\n"
               "def fit(z, gate: float = chi2_gate(GATE_PROB, 2), iterations: int = 15):\n"
               "    width_px = 23.0\n    gate_px: float = 6.0\n    return z\n")
    assert typed_gates(derived) == []
    from scipy.stats import chi2

    from envisat_pose.gates import GATE_PROB, chi2_bound, chi2_gate

    assert chi2_gate(GATE_PROB, 2) == chi2.ppf(GATE_PROB, 2) and abs(chi2_gate(GATE_PROB, 2) - 23.0259) < 1e-4
    assert chi2_bound(1e-5, 2) == chi2.isf(1e-5, 2)
    with pytest.raises(ValueError, match="gate probability"):
        chi2_gate(1.0, 2)


def test_the_physics_checker_catches_a_second_builder():
    planted = ("def truth_dynamics(truth):\n    scen = from_dict(ScenarioConfig, truth.config)\n"
               "    return scen.orbit.mu_m3_s2, scen.target.gravity_gradient\n\n"
               "def by_keys(truth):\n    c = truth.config\n"
               "    return float(c['orbit']['mu_m3_s2']), c['target']['gravity_gradient']\n\n"
               "def track(cfg):\n    return Tracker(mu_m3_s2=cfg.orbit.mu_m3_s2, gravity_gradient=cfg.gravity_gradient)\n")
    assert physics_builders(planted) == [1, 5]
    assert physics_builders(open(os.path.join(ROOT, ONBOARD_FILE), encoding="utf-8").read())  # the home
    assert filter_side(os.path.join("tests", "pipelines", "test_x.py")) and filter_side(os.path.join("bench", "x.py"))
    assert not filter_side(os.path.join("datagen", "truth.py"))


def test_the_band_checker_catches_a_band_typed_by_hand():
    planted = ("NEES_BAND_12 = (4.404, 23.337)  # chi-square 12 dof\n"
               "def consistent(nis):\n    return 0.216 < nis < 9.348\n"
               "lo_nis, hi_nis = 1.237, 14.449\n"
               "if mean_nees > 26.217:\n    pass\n")
    assert typed_bands(planted) == [1, 3, 4, 5]
    derived = ("from scipy.stats import chi2\nNEES_BAND = tuple(chi2.ppf([0.025, 0.975], 12))\n"
               "FLOORS = {'nees': (8.0, 16.0)}\nnees_window_s = 60.0\n")
    assert typed_bands(derived) == []
    from scipy.stats import chi2

    from envisat_pose.analysis.recording_layout import NEES_BAND_12

    assert NEES_BAND_12 == tuple(chi2.ppf([0.025, 0.975], 12))


def test_the_app_import_checker_catches_a_bench_using_a_verb():
    planted = ("def cfg():\n    from envisat_pose.app.run import run_config\n    return run_config('default')\n"
               "import envisat_pose.app.cli\nfrom filtering import fast\n")
    assert app_imports("bench/x.py", planted) == [2, 4, 5]
    assert app_imports("bench/x.py", "from envisat_pose.pipelines.runs.run_config import RunConfig\n") == []
    assert "scripts" in EXTRA_FOLDERS and "bench" in EXTRA_FOLDERS


# ---------------------------------------------------------------- thin verbs

VERB_MAX_LINES = 160  # issue 39: a verb parses flags, resolves one config, calls one pipeline function, prints
# Verb files over the limit today (their line counts when the guard came in, issue 39). The list only shrinks:
# a file on it may not grow past its count, one that comes down to the limit must leave the list
# (test_long_verbs_are_still_long), and a file not on it may not pass VERB_MAX_LINES.
LONG_VERBS: dict[str, int] = {}


def verb_lengths(root: str = ROOT) -> dict[str, int]:
    """{repository-relative path: lines} of every .py file of app/. Every file counts, cli.py (the dispatcher)
    and helpers included: the app layer is thin as a whole, so a helper of the verbs lives below it."""
    out = {}
    for dirpath, dirnames, filenames in os.walk(os.path.join(root, "app")):
        dirnames[:] = [d for d in dirnames if d != "__pycache__"]
        for name in filenames:
            if name.endswith(".py"):
                path = os.path.join(dirpath, name)
                with open(path, encoding="utf-8") as fh:
                    out[os.path.relpath(path, root)] = len(fh.read().splitlines())
    return out


def thick_verbs(lengths: dict[str, int], allowed: dict[str, int] = LONG_VERBS) -> dict[str, str]:
    """{file: why} of the verb files over their limit: VERB_MAX_LINES, or the count a listed file had."""
    out = {}
    for rel, n in lengths.items():
        limit = allowed.get(rel, VERB_MAX_LINES)
        if n > limit:
            out[rel] = f"{n} lines, over {limit}" + (" (its count on LONG_VERBS: it may only shrink)"
                                                     if rel in allowed else "")
    return out


def test_every_verb_file_stays_thin():
    assert thick_verbs(verb_lengths()) == {}, "move the work into a pipeline (pipelines/) or analysis/"


def test_long_verbs_are_still_long():
    """An entry of LONG_VERBS whose file is gone or back within the limit is stale: delete it."""
    lengths = verb_lengths()
    stale = [f for f in LONG_VERBS if lengths.get(f, 0) <= VERB_MAX_LINES]
    assert stale == [], f"{stale} are within {VERB_MAX_LINES} lines now (or gone): remove them from LONG_VERBS"


def test_the_verb_length_checker_sees_a_thick_verb(tmp_path):
    (tmp_path / "app").mkdir()
    (tmp_path / "app" / "thin.py").write_text("x = 1\n" * VERB_MAX_LINES)
    (tmp_path / "app" / "thick.py").write_text("x = 1\n" * (VERB_MAX_LINES + 1))
    (tmp_path / "app" / "listed.py").write_text("x = 1\n" * 201)
    lengths = verb_lengths(str(tmp_path))
    assert lengths[os.path.join("app", "thin.py")] == VERB_MAX_LINES
    found = thick_verbs(lengths, {os.path.join("app", "listed.py"): 200})
    assert sorted(found) == [os.path.join("app", "listed.py"), os.path.join("app", "thick.py")]
    thick = os.path.join("app", "thick.py")
    assert thick_verbs(lengths, {os.path.join("app", "listed.py"): 201}) == {thick: "161 lines, over 160"}


# ---------------------------------------------------------------- short functions

FUNCTION_MAX_LINES = 80  # issue 50: a function's steps get names; a longer one is several jobs in one body
# Functions over the limit that other engineers hold now: {"path:qualified name": why}. An entry must still be
# over the limit (test_pending_long_functions_are_still_long), so it is deleted with the split.
PENDING_LONG_FUNCTIONS: dict[str, str] = {}


def is_numba_kernel(node: ast.AST) -> bool:
    """A function compiled by numba (@njit, @jit, @numba.njit(...), ...): one loop body the compiler fuses, exempt
    from the limit."""
    for dec in getattr(node, "decorator_list", ()):
        target = dec.func if isinstance(dec, ast.Call) else dec
        name = target.attr if isinstance(target, ast.Attribute) else getattr(target, "id", "")
        if name in ("njit", "jit", "vectorize", "guvectorize", "stencil"):
            return True
    return False


def function_lengths(source: str, path: str = "<source>") -> dict[str, int]:
    """{qualified name: lines from `def` to its last line} of every function and method of a source, nested ones
    included (Outer.inner), numba kernels apart."""
    out = {}

    def walk(node, prefix):
        for child in ast.iter_child_nodes(node):
            if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
                name = f"{prefix}{child.name}"
                if not isinstance(child, ast.ClassDef) and not is_numba_kernel(child):
                    out[name] = child.end_lineno - child.lineno + 1
                walk(child, f"{name}.")
            else:
                walk(child, prefix)

    walk(parse(source, path), "")
    return out


def long_functions(root: str = ROOT) -> dict[str, int]:
    """{"path:qualified name": lines} of the package's functions over FUNCTION_MAX_LINES."""
    out = {}
    for path, _ in source_files(root):
        rel = os.path.relpath(path, root)
        with open(path, encoding="utf-8") as fh:
            for name, n in function_lengths(fh.read(), rel).items():
                if n > FUNCTION_MAX_LINES:
                    out[f"{rel}:{name}"] = n
    return out


def test_no_function_over_the_limit():
    """Floor of issue 50: 0 functions over FUNCTION_MAX_LINES lines outside numba kernels (those pending apart)."""
    found = {k: n for k, n in long_functions().items() if k not in PENDING_LONG_FUNCTIONS}
    assert found == {}, f"split these into named steps (<= {FUNCTION_MAX_LINES} lines each): {found}"


def test_pending_long_functions_are_still_long():
    stale = sorted(set(PENDING_LONG_FUNCTIONS) - set(long_functions()))
    assert stale == [], f"{stale} are within {FUNCTION_MAX_LINES} lines now (or gone): remove them from the list"


def test_the_function_length_checker_sees_a_long_function_and_exempts_a_kernel():
    body = "    x = 1\n" * FUNCTION_MAX_LINES
    source = ("import numba\n\n\ndef short():\n" + body[: -len("    x = 1\n")] +
              "\n\nclass A:\n    def long(self):\n" + "        x = 1\n" * FUNCTION_MAX_LINES +
              "\n\n@numba.njit(cache=True)\ndef kernel():\n" + body +
              "\n\ndef outer():\n    def inner():\n" + "        x = 1\n" * FUNCTION_MAX_LINES + "    return inner\n")
    lengths = function_lengths(source)
    assert lengths["short"] == FUNCTION_MAX_LINES and lengths["A.long"] == FUNCTION_MAX_LINES + 1
    assert "kernel" not in lengths and lengths["outer.inner"] == FUNCTION_MAX_LINES + 1
    assert lengths["outer"] == FUNCTION_MAX_LINES + 3


# ---------------------------------------------------------------- the slow lane's list (tests/conftest.py)

def slow_ids(root: str = ROOT) -> tuple[str, ...]:
    """The SLOW tuple of tests/conftest.py, read without importing it."""
    tree = parse(open(os.path.join(root, "tests", "conftest.py"), encoding="utf-8").read())
    for node in tree.body:
        if isinstance(node, ast.Assign) and any(isinstance(t, ast.Name) and t.id == "SLOW" for t in node.targets):
            return tuple(ast.literal_eval(node.value))
    raise AssertionError("tests/conftest.py defines no SLOW")


def missing_test(nodeid: str, root: str = ROOT) -> str | None:
    """Why a node id names no test (None: it does): the file, the test function (or Class::method) in it, and,
    for an id with [...], a parametrized test."""
    path, _, rest = nodeid.partition("::")
    full = os.path.join(root, *path.split("/"))
    if not os.path.isfile(full):
        return f"{nodeid}: no file {path}"
    names = rest.split("[", 1)[0].split("::")
    scope = parse(open(full, encoding="utf-8").read()).body
    node = None
    for name in names:
        node = next((n for n in scope if isinstance(n, (ast.FunctionDef, ast.ClassDef)) and n.name == name), None)
        if node is None:
            return f"{nodeid}: no {name} in {path}"
        scope = node.body
    if "[" in rest and not any("parametrize" in ast.unparse(d) for d in node.decorator_list):
        return f"{nodeid}: {names[-1]} is not parametrized"
    return None


def test_every_slow_id_names_a_test():
    ids = slow_ids()
    assert len(set(ids)) == len(ids), "SLOW lists a test twice"
    assert [why for i in ids if (why := missing_test(i))] == []


def test_the_slow_list_checker_sees_a_stale_id():
    here = "tests/test_architecture.py"
    assert missing_test(f"{here}::test_every_slow_id_names_a_test") is None
    assert missing_test(f"{here}::test_one_home_for_each_concept[typed_gates]") is None
    assert "no test_gone" in missing_test(f"{here}::test_gone")
    assert "no file" in missing_test("tests/nowhere/test_x.py::test_a")
    assert "not parametrized" in missing_test(f"{here}::test_every_slow_id_names_a_test[x]")


# modules whose every test is slow: the web viewer's screenshot (its one test drives Chromium), the wheel's
# install into a fresh venv, and DDP's two processes (one end-to-end test each)
ONLY_SLOW = {"tests/app/test_viewer_screenshot.py", "tests/test_wheel_install.py", "tests/perception/test_ddp.py"}


def test_every_test_module_keeps_a_fast_test():
    """The fast lane (make test) still exercises every test module: none is slow in all its tests (ONLY_SLOW
    apart)."""
    slow = set(slow_ids())
    bare = []
    for dirpath, _, files in os.walk(os.path.join(ROOT, "tests")):
        for f in files:
            if not (f.startswith("test_") and f.endswith(".py")):
                continue
            path = os.path.join(dirpath, f)
            rel = os.path.relpath(path, ROOT).replace(os.sep, "/")
            tests = [n for n in parse(open(path, encoding="utf-8").read()).body
                     if isinstance(n, ast.FunctionDef) and n.name.startswith("test_")]
            fast = [n for n in tests if f"{rel}::{n.name}" not in slow
                    and not any("mark.slow" in ast.unparse(d) for d in n.decorator_list)]
            if tests and not fast and rel not in ONLY_SLOW:
                bare.append(rel)
    assert bare == []


def test_the_run_config_checker_catches_a_hand_built_run():
    planted = "def cfg(w):\n    return loop.finish_config(from_dict(loop.RunConfig, {'weights': w}))\n"
    assert run_configs_built(planted) == [2]
    assert run_configs_built("cfg = run_config('default', {'duration_s': 4.0})\n") == []


# ---------------------------------------------------------------- each constant and the manifest's reader once (issue 54)

CONSTANT_NAME = re.compile(r"^[A-Z][A-Z0-9_]*$")  # a module's public constant (a private cache is no constant)
# Copies in files other engineers own now: {file: {NAME, ...}}. An entry must still hold a copy
# (`test_pending_constants_are_still_there`), so it is deleted with the fix.
PENDING_CONSTANTS: dict[str, set[str]] = {}


def _literal_key(node: ast.AST):
    """A constant's value as compared across modules (a string as its characters, so 'ABCDEFGH' equals the tuple
    of its letters; a list, tuple or set as a tuple of its items), or None for no plain literal (or an empty one:
    a cache, not a constant)."""
    try:
        value = ast.literal_eval(node)
    except (ValueError, TypeError, SyntaxError, MemoryError, RecursionError):
        return None
    if isinstance(value, (list, tuple)):
        value = tuple(value)
    elif isinstance(value, (set, frozenset)):
        value = tuple(sorted(value, key=repr))
    elif isinstance(value, dict):
        value = tuple(sorted((repr(k), repr(v)) for k, v in value.items()))
    if isinstance(value, str):
        value = tuple(value)
    if isinstance(value, tuple) and not value:
        return None
    return repr(value)


def literal_constants(source: str) -> list[tuple[int, str, str]]:
    """(line, NAME, value key) of each module-level constant bound to a plain literal (CONSTANT_NAME = literal)."""
    out = []
    for node in parse(source).body:
        if isinstance(node, ast.Assign):
            targets = node.targets
        elif isinstance(node, ast.AnnAssign) and node.value is not None:
            targets = [node.target]
        else:
            continue
        key = _literal_key(node.value)
        out += [(node.lineno, t.id, key) for t in targets
                if key is not None and isinstance(t, ast.Name) and CONSTANT_NAME.match(t.id)]
    return out


def _distinctive(key: str) -> bool:
    """Whether equal values under two names are one constant typed twice: a string of 4 or more characters or a
    container of 2 or more items (a number or a short word may be two things that agree)."""
    value = ast.literal_eval(key)
    return isinstance(value, tuple) and (len(value) >= 4 or (len(value) >= 2 and not all(
        isinstance(v, str) and len(v) == 1 for v in value)))


def constant_copies(root: str = ROOT) -> dict[str, list[str]]:
    """{value: ['file:line NAME', ...]} of every literal constant typed in two modules: the same name bound to an
    equal value, or an equal distinctive value under any names. The package's modules are compared with one
    another, and a bench's or a script's with the package's (benches keep their own knobs; a copy of the
    package's constant is a copy)."""
    package = {os.path.relpath(p, root) for p, _ in source_files(root)}
    by_value: dict[str, list[tuple[str, int, str]]] = {}
    for rel in checked_files(root):
        with open(os.path.join(root, rel), encoding="utf-8") as fh:
            for line, name, key in literal_constants(fh.read()):
                if name not in PENDING_CONSTANTS.get(rel, ()):
                    by_value.setdefault(key, []).append((rel, line, name))
    found = {}
    for key, where in by_value.items():
        if not _distinctive(key):
            names = [n for _, _, n in where]
            where = [w for w in where if names.count(w[2]) > 1]
        if len({rel for rel, _, _ in where}) > 1 and any(rel in package for rel, _, _ in where):
            found[key] = [f"{rel}:{line} {name}" for rel, line, name in sorted(where)]
    return found


MANIFEST_FILE = re.compile(r"([^\s]*[/\\])?manifest\.json")  # the file's name typed as a path (not in a sentence)
# calls that open, read or write the file they are given (a manifest's path given to one reaches the manifest)
MANIFEST_ACCESS = ("open", "read_text", "read_bytes", "load", "loads", "atomic_write_text", "atomic_path",
                   "write_text", "write_bytes")


def manifest_reads(source: str) -> list[int]:
    """Lines that reach a manifest.json by themselves instead of through its one reader (resumable.read_manifest,
    and for a dataset shard_reader.load_dataset_manifest) or its one writer (ResumableJob): the file's name typed
    as a path, the home's constant MANIFEST, or a path from resumable.manifest_path (directly or through names
    bound to it) opened, read or written. Testing whether a manifest exists, or hashing it, through manifest_path
    is fine."""
    tree = parse(source)
    lines = [n.lineno for n in walk(tree) if isinstance(n, ast.Constant) and isinstance(n.value, str)
             and MANIFEST_FILE.fullmatch(n.value)]
    lines += [n.lineno for n in walk(tree) if (isinstance(n, ast.Name) and n.id == "MANIFEST")
              or (isinstance(n, ast.Attribute) and n.attr == "MANIFEST")]
    lines += [n.lineno for n in walk(tree) if isinstance(n, (ast.Import, ast.ImportFrom))
              and any(a.name == "MANIFEST" for a in n.names)]

    def via_path(node, names):
        return any((isinstance(n, ast.Call) and _called_name(n) == "manifest_path")
                   or (isinstance(n, ast.Name) and n.id in names) for n in walk(node))

    tainted: set[str] = set()  # names bound to a manifest's path
    while True:
        more = {t.id for n in walk(tree) if isinstance(n, (ast.Assign, ast.AnnAssign)) and n.value is not None
                and via_path(n.value, tainted)
                for t in (n.targets if isinstance(n, ast.Assign) else [n.target]) if isinstance(t, ast.Name)}
        if more <= tainted:
            break
        tainted |= more
    for n in walk(tree):
        if isinstance(n, ast.Call) and _called_name(n) in MANIFEST_ACCESS:
            operands = list(n.args) + [k.value for k in n.keywords]
            if isinstance(n.func, ast.Attribute):
                operands.append(n.func.value)
            if any(via_path(o, tainted) for o in operands):
                lines.append(n.lineno)
    return sorted(set(lines))


def manifest_readers(root: str = ROOT) -> dict[str, list[int]]:
    """{file: lines} of manifest_reads in the package, the benches and the scripts, the home apart."""
    found = {}
    for rel in checked_files(root):
        if rel == RESUMABLE_FILE:
            continue
        with open(os.path.join(root, rel), encoding="utf-8") as fh:
            lines = manifest_reads(fh.read())
        if lines:
            found[rel] = lines
    return found


def test_each_literal_constant_is_defined_in_one_module():
    found = constant_copies()
    assert found == {}, f"constants typed in two modules: {found}; define each once, in the lowest layer that " \
                        "needs it, and import it"


def test_pending_constants_are_still_there():
    """A pending entry whose copy is gone is stale: delete it from PENDING_CONSTANTS."""
    saved = {rel: set(names) for rel, names in PENDING_CONSTANTS.items()}
    try:
        PENDING_CONSTANTS.clear()
        found = {entry.split(":")[0] + " " + entry.split(" ")[1] for where in constant_copies().values()
                 for entry in where}
    finally:
        PENDING_CONSTANTS.update(saved)
    stale = sorted(f"{rel} {name}" for rel, names in saved.items() for name in names if f"{rel} {name}" not in found)
    assert stale == [], f"{stale} no longer copy a constant; remove them from PENDING_CONSTANTS"


def test_the_constant_checker_sees_a_copy_under_either_name_and_keeps_a_bench_knob(tmp_path):
    for folder in ("envisat_pose", "perception", "datagen", "bench"):
        (tmp_path / folder).mkdir()
    (tmp_path / "envisat_pose" / "geometry.py").write_text('CORNER_NAMES = ("A", "B", "C", "D")\nN = 8\n')
    (tmp_path / "perception" / "evaluate.py").write_text('CORNER_NAMES = "ABCD"\nN = 8\nM = 8\n_CACHE = {}\n')
    (tmp_path / "datagen" / "render.py").write_text('CAMERA_NAME = "chaser_cam"\n_CACHE = {}\n')
    (tmp_path / "datagen" / "sim.py").write_text('SCENE_CAMERA = "chaser_cam"\nLEVELS = ("none", "low")\n')
    (tmp_path / "bench" / "a.py").write_text('LEVELS = ["none", "low"]\nREPEATS = 5\n')
    (tmp_path / "bench" / "b.py").write_text("REPEATS = 5\n")
    geometry, evaluate = os.path.join("envisat_pose", "geometry.py"), os.path.join("perception", "evaluate.py")
    render, sim, bench = (os.path.join(*p) for p in (("datagen", "render.py"), ("datagen", "sim.py"), ("bench", "a.py")))
    assert constant_copies(str(tmp_path)) == {
        repr(tuple("ABCD")): [f"{geometry}:1 CORNER_NAMES", f"{evaluate}:1 CORNER_NAMES"],  # a tuple and a string
        "8": [f"{geometry}:2 N", f"{evaluate}:2 N"],  # one name, one number: M = 8 is another thing
        repr(tuple("chaser_cam")): [f"{render}:1 CAMERA_NAME", f"{sim}:1 SCENE_CAMERA"],  # one value, two names
        repr(("none", "low")): [f"{bench}:1 LEVELS", f"{sim}:2 LEVELS"]}  # a bench copying the package's


def test_only_the_manifest_reader_reaches_a_manifest():
    found = manifest_readers()
    assert found == {}, f"manifest.json reached outside its reader at {found}: read a dataset's with " \
                        "shard_reader.load_dataset_manifest (resumable.read_manifest for any job's)"


def test_the_manifest_reader_checker_sees_each_way_round_it():
    planted = ("import json, os\nfrom envisat_pose.resumable import MANIFEST, manifest_path\n\n"
               "def config(d):\n    return json.load(open(os.path.join(d, 'manifest.json')))['config']\n\n"
               "def mode(d):\n    path = manifest_path(d)\n    with open(path) as fh:\n        return json.load(fh)\n\n"
               "def count(d):\n    return len(pathlib.Path(manifest_path(d)).read_text()) + len(f'{d}/manifest.json')\n\n"
               "def record(d, m):\n    atomic_write_text(manifest_path(d), json.dumps(m))\n")
    assert manifest_reads(planted) == [2, 5, 9, 13, 16]
    fine = ("import os\nfrom envisat_pose.resumable import manifest_path\nfrom envisat_pose.io import sha256_file\n\n"
            "def made(d):\n    return os.path.isfile(manifest_path(d)) and sha256_file(manifest_path(d))\n\n"
            "HELP = 'a dataset folder (shards + manifest.json)'\n")
    assert manifest_reads(fine) == []
    with open(os.path.join(ROOT, RESUMABLE_FILE), encoding="utf-8") as fh:
        assert manifest_reads(fh.read())  # the home


# ---------------------------------------------------------------- the trainer's private names stay inside it

# Issue 54: every training loop runs through perception/train.py's Trainer, so no module outside the trainer's own
# (the package's, the benches', the scripts') imports a private name of theirs: the step `_train_step` imported is a
# training loop of its own. The tests may (tests/perception/test_losses.py checks the step itself).
TRAINER_MODULES = ("envisat_pose.perception.train", "envisat_pose.perception.train_run",
                   "envisat_pose.perception.trainer_hooks")


def _private(name: str) -> bool:
    return name.startswith("_") and not name.startswith("__")


def private_trainer_imports(path: str, module: str, source: str) -> list[int]:
    """Lines where a module outside TRAINER_MODULES imports a private name of one (`from ...train import
    _train_step`, relative imports resolved) or reads one off a trainer module it imported (`train._train_step`)."""
    if module in TRAINER_MODULES:
        return []
    lines = {line for line, name in imported_modules(path, module, source)
             if name.rpartition(".")[0] in TRAINER_MODULES and _private(name.rpartition(".")[2])}
    tree, bound = parse(source, path), set(TRAINER_MODULES)  # the names a trainer module is read through
    for node in walk(tree):
        if isinstance(node, ast.Import):
            bound |= {a.asname for a in node.names if a.asname and a.name in TRAINER_MODULES}
        elif isinstance(node, ast.ImportFrom):
            full = [name for _, name in imported_modules(path, module, ast.unparse(node))][1:]
            bound |= {a.asname or a.name for a, name in zip(node.names, full) if name in TRAINER_MODULES}
    lines |= {node.lineno for node in walk(tree)
              if isinstance(node, ast.Attribute) and _private(node.attr) and ast.unparse(node.value) in bound}
    return sorted(lines)


def test_no_private_trainer_name_is_imported_outside_the_trainer():
    """Floor of issue 54: 0 imports of a trainer module's private name (its step above all) outside the trainer,
    in the package, the benches and the scripts."""
    modules = {os.path.relpath(p, ROOT): m for p, m in source_files()}
    found = {}
    for rel in checked_files():
        with open(os.path.join(ROOT, rel), encoding="utf-8") as fh:
            lines = private_trainer_imports(rel, modules.get(rel, "outside"), fh.read())
        if lines:
            found[rel] = lines
    assert found == {}, f"run these through perception.train.Trainer instead: {found}"


def test_the_trainer_privacy_checker_sees_each_way_in():
    fine_tune = (os.path.join("pipelines", "adaptation", "fine_tune.py"), "envisat_pose.pipelines.adaptation.fine_tune")
    planted = {
        "from envisat_pose.perception.train import TrainConfig, _train_step, cosine_factor\n": [1],
        "import envisat_pose.perception.train as tm\n\ndef f(m):\n    return tm._train_step(m)\n": [4],
        "from envisat_pose.perception import train as t\nx = t._dist()\n": [2],
        "import envisat_pose.perception.train\nx = envisat_pose.perception.train._autocast\n": [2],
        "from envisat_pose.perception.train import Trainer, lr_at\n"
        "from envisat_pose.perception import trainer_hooks as th\nname = th.Hook.__name__\n": [],
    }
    for source, lines in planted.items():
        assert private_trainer_imports(*fine_tune, source) == lines, source
    relative = "from .train import _train_step\n"
    evaluate = (os.path.join("perception", "evaluate.py"), "envisat_pose.perception.evaluate")
    assert private_trainer_imports(*evaluate, relative) == [1]
    assert private_trainer_imports(os.path.join("perception", "train.py"), "envisat_pose.perception.train",
                                   relative) == []  # the trainer's own modules share theirs


# ---------------------------------------------------------------- a config is validated when built (issue 54)

CONFIG_HOME = os.path.join("envisat_pose", "config_fields.py")  # config.Config: __post_init__ calls validate("")
# Configs in files other engineers own now, still to derive from config.Config: `test_pending_config_bases_...`
# fails once one does, so its entry is deleted with the change.
PENDING_CONFIG_BASES: dict[str, set[str]] = {}
# Callers of the deprecated Cfg.from_scenario in files other engineers own now (same rule: deleted with the fix).
PENDING_FROM_SCENARIO: set[str] = set()


def _class_bases(node: ast.ClassDef) -> set[str]:
    return {b.attr if isinstance(b, ast.Attribute) else getattr(b, "id", "") for b in node.bases}


def _calls_super_post_init(fn: ast.AST) -> bool:
    return any(isinstance(n, ast.Call) and isinstance(n.func, ast.Attribute) and n.func.attr == "__post_init__"
               and isinstance(n.func.value, ast.Call) and getattr(n.func.value.func, "id", "") == "super"
               for n in walk(fn))


def config_base_problems(sources: dict[str, str]) -> tuple[dict[str, dict[str, str]], set[str]]:
    """({file: {class: why}}, the names of the classes that derive from config.Config, through any chain of
    bases): a class that defines validate() but does not derive from Config (nothing validates it when built),
    and a Config whose own __post_init__ never calls super().__post_init__() (which validates)."""
    classes = [(rel, node) for rel, source in sources.items() for node in walk(parse(source))
               if isinstance(node, ast.ClassDef)]
    derived, grown = {"Config"}, True
    while grown:
        new = {node.name for _, node in classes if _class_bases(node) & derived} - derived
        derived, grown = derived | new, bool(new)
    found: dict[str, dict[str, str]] = {}
    for rel, node in classes:
        methods = {f.name: f for f in node.body if isinstance(f, ast.FunctionDef)}
        if rel == CONFIG_HOME and node.name == "Config":
            continue
        if "validate" in methods and node.name not in derived:
            found.setdefault(rel, {})[node.name] = f"line {node.lineno}: defines validate() but does not derive " \
                                                   "from config.Config (validated when built)"
        elif node.name in derived and "__post_init__" in methods and not _calls_super_post_init(
                methods["__post_init__"]):
            found.setdefault(rel, {})[node.name] = f"line {node.lineno}: its __post_init__ skips " \
                                                   "super().__post_init__() (the validation)"
    return found, derived


def config_from_scenario_calls(source: str, config_names: set[str]) -> list[int]:
    """Lines calling the deprecated `Cfg.from_scenario(...)` of a config class (a name in config_names or ending
    in Config; Tracker.from_scenario builds a tracker, not a config)."""
    lines = []
    for node in walk(parse(source)):
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.func.attr == "from_scenario":
            owner = node.func.value
            name = owner.attr if isinstance(owner, ast.Attribute) else getattr(owner, "id", "")
            if name in config_names or name.endswith("Config"):
                lines.append(node.lineno)
    return lines


def package_config_problems():
    sources = {}
    for path, _ in source_files():
        with open(path, encoding="utf-8") as fh:
            sources[os.path.relpath(path, ROOT)] = fh.read()
    return config_base_problems(sources)


def from_scenario_calls() -> dict[str, list[int]]:
    """{file: lines} of the calls of a config's deprecated from_scenario in the package, the benches and the
    scripts."""
    _, names = package_config_problems()
    found = {}
    for rel in checked_files():
        with open(os.path.join(ROOT, rel), encoding="utf-8") as fh:
            lines = config_from_scenario_calls(fh.read(), names)
        if lines:
            found[rel] = lines
    return found


def test_every_config_is_validated_when_built():
    """Floor of issue 54: every class of the package that defines validate() derives from config.Config, and
    none skips its validation (0 besides PENDING_CONFIG_BASES, which only shrinks)."""
    problems, _ = package_config_problems()
    left = {rel: {name: why for name, why in classes.items() if name not in PENDING_CONFIG_BASES.get(rel, set())}
            for rel, classes in problems.items()}
    assert {rel: c for rel, c in left.items() if c} == {}


def test_pending_config_bases_are_still_missing():
    problems, _ = package_config_problems()
    stale = {rel: sorted(names - set(problems.get(rel, {}))) for rel, names in PENDING_CONFIG_BASES.items()}
    assert {rel: n for rel, n in stale.items() if n} == {}, "derive from config.Config now: remove from PENDING"


def test_no_config_is_built_by_the_deprecated_from_scenario():
    """Floor of issue 54: a job's config is built by its constructor (or pipelines.jobs.resolve_job for a file and
    flags), never by the deprecated Cfg.from_scenario (0 calls in the package, the benches and the scripts besides
    PENDING_FROM_SCENARIO, whose entries must still call it)."""
    found = from_scenario_calls()
    assert {rel: lines for rel, lines in found.items() if rel not in PENDING_FROM_SCENARIO} == {}
    assert sorted(PENDING_FROM_SCENARIO - set(found)) == [], "no longer calls from_scenario: remove from PENDING"


def test_the_config_checkers_see_a_planted_config_outside_the_base_and_a_deprecated_call():
    planted = {
        CONFIG_HOME: "class Config:\n    def __post_init__(self):\n        self.validate('')\n\n"
                     "    def validate(self, prefix=''):\n        pass\n",
        "a.py": "from envisat_pose import config\n\nclass Job(config.Config):\n    def validate(self, prefix=''):\n"
                "        pass\n\nclass Loose:\n    def validate(self, prefix=''):\n        pass\n\n"
                "class Section(Job):\n    def validate(self, prefix=''):\n        pass\n\n"
                "class Filled(Section):\n    def __post_init__(self):\n        self.x = 1\n\n"
                "class Fills(Config):\n    def __post_init__(self):\n        super().__post_init__()\n",
    }
    problems, derived = config_base_problems(planted)
    assert {name: why.split(":")[0] for name, why in problems["a.py"].items()} == {"Loose": "line 7",
                                                                                   "Filled": "line 15"}
    assert set(problems) == {"a.py"} and {"Job", "Section", "Filled", "Fills"} <= derived
    calls = ("cfg = RunConfig.from_scenario('default')\nt = Tracker.from_scenario('default')\n"
             "m = campaign.MonteCarloConfig.from_scenario('eclipse', runs=2)\nj = Job.from_scenario('x')\n")
    assert config_from_scenario_calls(calls, derived) == [1, 3, 4]


# ---------------------------------------------------------------- modules with one job (issue 54, item 6)

MODULE_MAX_LINES = 500  # issue 54: a module over it holds several jobs; split it by job into modules of its folder
# filtering/fast.py: the numba kernels, each a fused loop the compiler takes whole, and the helpers they inline
LONG_MODULES_EXEMPT = (os.path.join("filtering", "fast.py"),)


def module_length_problem(rel: str, source: str) -> str | None:
    """Why a module of the package (rel: its repository-relative path) is too long ("N lines, over the limit"), or
    None: within MODULE_MAX_LINES lines, or exempt (LONG_MODULES_EXEMPT)."""
    n = len(source.splitlines())
    if n <= MODULE_MAX_LINES or rel in LONG_MODULES_EXEMPT:
        return None
    return f"{n} lines, over {MODULE_MAX_LINES}"


def long_modules(root: str = ROOT) -> dict[str, str]:
    """{repository-relative path: why} of the package's modules over the limit (source_files: the core and the layer
    folders; bench/, scripts/ and tests/ are not the package's modules)."""
    found = {}
    for path, _ in source_files(root):
        rel = os.path.relpath(path, root)
        with open(path, encoding="utf-8") as fh:
            why = module_length_problem(rel, fh.read())
        if why:
            found[rel] = why
    return found


def test_no_module_over_the_limit():
    """Floor of issue 54: 0 modules of the package over MODULE_MAX_LINES lines, the numba kernels apart (and the
    exemption names a module that exists)."""
    assert long_modules() == {}, f"split these by job into modules of their folder (<= {MODULE_MAX_LINES} lines)"
    assert all(os.path.isfile(os.path.join(ROOT, rel)) for rel in LONG_MODULES_EXEMPT)


def test_the_module_length_checker_sees_a_long_module(tmp_path):
    planted = "x = 1\n" * (MODULE_MAX_LINES + 1)  # a 501-line module
    assert module_length_problem(os.path.join("datagen", "render.py"), planted) == "501 lines, over 500"
    assert module_length_problem(os.path.join("datagen", "render.py"), planted[: -len("x = 1\n")]) is None
    assert module_length_problem(os.path.join("filtering", "fast.py"), planted) is None  # the kernels
    for folder in ("datagen", "filtering", "envisat_pose", "bench", "scripts", "tests"):
        (tmp_path / folder).mkdir()
        (tmp_path / folder / "long.py").write_text(planted)
    (tmp_path / "filtering" / "fast.py").write_text(planted)
    assert long_modules(str(tmp_path)) == {os.path.join(folder, "long.py"): "501 lines, over 500"
                                           for folder in ("datagen", "filtering", "envisat_pose")}


# ---------------------------------------------------------------- one meaning of "look" (issue 54, item 5)

# A look is one way the factory renders images: a weighted generate config in a mix (`envisat train --looks`, its
# [[look]] tables, pipelines/detector/look_mix.py). A sample's drawn materials and lights are its appearance
# (datagen/appearance.py: Appearance, draw_materials), a camera's response curve and blur its camera response
# (envisat_pose/camera_response.py, pipelines/adaptation/edge_response.py): no name calls those a look.
LOOK_MIX_HOME = os.path.join("pipelines", "detector", "look_mix.py")
# the mix's users, which hold looks of their own (variables, fields, the --looks flag) besides look_mix's names;
# an entry must still spell "look" (`test_look_means_one_thing`)
LOOK_MIX_USERS = (
    os.path.join("pipelines", "detector", "online.py"),       # online_batches(looks, ...)
    os.path.join("pipelines", "detector", "render_pool.py"),  # the renderer processes of a mix's looks
    os.path.join("pipelines", "detector", "train.py"),        # OnlineConfig.looks
    os.path.join("app", "train.py"),                          # envisat train --looks
    os.path.join("scripts", "gpu_train.py"),                  # the GPU recipe's looks file (online_looks)
    os.path.join("bench", "train_speed.py"),                  # online_batches over OnlineConfig.looks
    os.path.join("bench", "silhouette_bias.py"),              # its looks: plain materials, appearance on, sequence
)


def says_look(name: str) -> bool:
    """Whether an identifier (or a module's name) holds the word part "look", "lookup" and its kin apart."""
    return "look" in name.lower().replace("lookup", "")


def look_mix_names(root: str = ROOT) -> frozenset[str]:
    """What any module may spell of the mix: the module's name and the names look_mix.py defines at its top level."""
    with open(os.path.join(root, LOOK_MIX_HOME), encoding="utf-8") as fh:
        tree = parse(fh.read())
    names = {"look_mix"}
    for node in tree.body:
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            names.add(node.name)
        elif isinstance(node, (ast.Assign, ast.AnnAssign)):
            targets = node.targets if isinstance(node, ast.Assign) else [node.target]
            names |= {n.id for t in targets for n in walk(t) if isinstance(n, ast.Name)}
    return frozenset(names)


def spelled_names(source: str):
    """(line, identifier) of every name a module spells: names, attributes, definitions, arguments, keywords, what
    it imports (each part of a dotted module) and under which names. Strings (a flag, a JSON key) are not names."""
    for node in walk(parse(source)):
        line = getattr(node, "lineno", 0)
        if isinstance(node, ast.Name):
            yield line, node.id
        elif isinstance(node, ast.Attribute):
            yield line, node.attr
        elif isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            yield line, node.name
        elif isinstance(node, ast.arg):
            yield line, node.arg
        elif isinstance(node, ast.keyword) and node.arg:
            yield line, node.arg
        elif isinstance(node, ast.alias):
            yield from ((line, part) for part in node.name.split(".") + [node.asname or ""] if part)
        elif isinstance(node, ast.ImportFrom) and node.module:
            yield from ((line, part) for part in node.module.split("."))
        elif isinstance(node, (ast.Global, ast.Nonlocal)):
            yield from ((line, name) for name in node.names)
        elif isinstance(node, ast.ExceptHandler) and node.name:
            yield line, node.name


def stray_look_names(rel: str, source: str, allowed: frozenset[str]) -> list[tuple[int, str]]:
    """(line, name), sorted, of the names that say "look" in a module (rel: its repository-relative path) outside the
    mix: none in LOOK_MIX_HOME or LOOK_MIX_USERS; elsewhere any but `allowed` (look_mix_names). The module's own
    path (its folders and file name) counts, at line 0."""
    if rel == LOOK_MIX_HOME or rel in LOOK_MIX_USERS:
        return []
    parts = [part.removesuffix(".py") for part in rel.split(os.sep)]
    found = {(0, part) for part in parts if says_look(part) and part not in allowed}
    found |= {(line, name) for line, name in spelled_names(source) if says_look(name) and name not in allowed}
    return sorted(found)


def stray_looks(root: str = ROOT) -> dict[str, list[tuple[int, str]]]:
    """{repository-relative path: stray_look_names} over the package, the benches and the scripts (checked_files)."""
    allowed, found = look_mix_names(root), {}
    for rel in checked_files(root):
        with open(os.path.join(root, rel), encoding="utf-8") as fh:
            names = stray_look_names(rel, fh.read(), allowed)
        if names:
            found[rel] = names
    return found


def test_look_means_one_thing():
    """Issue 54 item 5: "look" means one thing, a way the factory renders images in a mix (pipelines/detector/
    look_mix.py). 0 names saying "look" in the package, the benches and the scripts outside the mix's home and its
    users besides the names the mix defines (a material draw is an appearance, a camera's response and blur a
    camera response); every user listed exists and still spells a look."""
    assert stray_looks() == {}, "a material draw is an appearance, a response and blur a camera response"
    for rel in LOOK_MIX_USERS:
        with open(os.path.join(ROOT, rel), encoding="utf-8") as fh:
            assert any(says_look(name) for _, name in spelled_names(fh.read())), f"{rel}: no look: remove it"


def test_the_look_checker_sees_a_material_draw_and_a_response_called_a_look(tmp_path):
    allowed = frozenset({"look_mix", "WeightedLook", "read_looks"})
    planted = ("from envisat_pose.pipelines.detector.look_mix import WeightedLook, read_looks\n"
               "from envisat_pose.pipelines.adaptation import edge_look\n"
               "import envisat_pose.datagen.appearance as looks\n"
               "def with_look(view, look=None):\n"
               "    table.lookup(view)\n"
               "    view.look = ProcessLookupError\n"
               "    return draw(appearance='look', look_seed=1)\n"
               "class LookFit:\n"
               "    pass\n")
    assert stray_look_names(os.path.join("datagen", "factory.py"), planted, allowed) == [
        (2, "edge_look"), (3, "looks"), (4, "look"), (4, "with_look"), (6, "look"), (7, "look_seed"), (8, "LookFit")]
    assert stray_look_names(LOOK_MIX_USERS[0], planted, allowed) == []  # the mix's users hold looks
    assert stray_look_names(os.path.join("pipelines", "adaptation", "edge_look.py"), "x = 1\n", allowed) == [
        (0, "edge_look")]
    files = {LOOK_MIX_HOME: "LOOK_PERIOD = 100\n\ndef read_looks(path):\n    looks = path\n    return looks\n",
             os.path.join("bench", "mix.py"): "from envisat_pose.pipelines.detector.look_mix import read_looks\n"
                                              "looks = read_looks('x')\n",
             os.path.join("datagen", "edge_look.py"): "x = 1\n",
             os.path.join("app", "train.py"): "looks = 1\n",
             os.path.join("tests", "test_x.py"): "look = 1\n"}
    for rel, text in files.items():
        (tmp_path / rel).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / rel).write_text(text)
    assert look_mix_names(str(tmp_path)) == {"look_mix", "LOOK_PERIOD", "read_looks"}
    assert stray_looks(str(tmp_path)) == {os.path.join("bench", "mix.py"): [(2, "looks")],
                                          os.path.join("datagen", "edge_look.py"): [(0, "edge_look")]}


# ---------------------------------------------------------------- whole flags only (no abbreviations)

# Every command line of the repository (the verbs, the benches, the scripts, the tests' data makers) takes each flag
# only as spelled whole: argparse's default reads `--seed` as `--seeds` and `--dur` as `--duration-s`, so a typo
# silently means another flag. The one parser that refuses them: envisat_pose.whole_flags.WholeFlagParser (a
# subclass, so its calls are not argparse.ArgumentParser's); a file that cannot import the package (the standard-
# library-only scripts/gpu_layout.py) passes allow_abbrev=False itself.
WHOLE_FLAGS_FILE = os.path.join("envisat_pose", "whole_flags.py")


def abbreviating_parsers(source: str) -> list[int]:
    """Lines of argparse.ArgumentParser(...) calls (or a bare ArgumentParser imported from argparse) that do not pass
    allow_abbrev=False as a literal (a **kwargs that might hold it does not count)."""
    lines = []
    for node in walk(parse(source)):
        if isinstance(node, ast.Call) and _called_name(node) == "ArgumentParser":
            whole = any(k.arg == "allow_abbrev" and isinstance(k.value, ast.Constant) and k.value.value is False
                        for k in node.keywords)
            if not whole:
                lines.append(node.lineno)
    return sorted(lines)


def abbreviating_parser_files(root: str = ROOT) -> dict[str, list[int]]:
    """{file: lines} of abbreviating_parsers over the package, the benches, the scripts and the tests."""
    found = {}
    for rel in checked_files(root, EXTRA_FOLDERS + ("tests",)):
        with open(os.path.join(root, rel), encoding="utf-8") as fh:
            lines = abbreviating_parsers(fh.read())
        if lines:
            found[rel] = lines
    return found


def test_every_parser_takes_whole_flags_only():
    """0 argparse parsers that take abbreviated flags, anywhere in the repository: each is WholeFlagParser or
    passes allow_abbrev=False; WholeFlagParser itself refuses them."""
    assert abbreviating_parser_files() == {}, f"use {WHOLE_FLAGS_FILE}'s WholeFlagParser (or allow_abbrev=False)"
    from envisat_pose.whole_flags import WholeFlagParser

    assert WholeFlagParser().allow_abbrev is False


def test_the_parser_checker_sees_an_abbreviating_parser(tmp_path):
    planted = ("import argparse\nfrom argparse import ArgumentParser\n"
               "a = argparse.ArgumentParser(description='x')\n"
               "b = ArgumentParser()\n"
               "c = argparse.ArgumentParser(allow_abbrev=True)\n"
               "d = argparse.ArgumentParser(**opts)\n"
               "e = argparse.ArgumentParser(description='x', allow_abbrev=False)\n"
               "f = WholeFlagParser(description='x')\n"
               "def g(p: argparse.ArgumentParser) -> argparse.ArgumentParser:\n    return p\n")
    assert abbreviating_parsers(planted) == [3, 4, 5, 6]
    (tmp_path / "bench").mkdir()
    (tmp_path / "bench" / "x.py").write_text(planted)
    (tmp_path / "tests").mkdir()
    (tmp_path / "tests" / "make_x.py").write_text("import argparse\np = argparse.ArgumentParser()\n")
    (tmp_path / "app").mkdir()
    (tmp_path / "app" / "cli.py").write_text("p = WholeFlagParser(prog='envisat')\n")
    assert abbreviating_parser_files(str(tmp_path)) == {os.path.join("bench", "x.py"): [3, 4, 5, 6],
                                                        os.path.join("tests", "make_x.py"): [2]}
