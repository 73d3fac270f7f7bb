"""The package's shape (issue 14): no world is named outside its own modules, and no package
imports another that imports it back.

World-specific modules are the registry (``rlbackdoors/worlds/``), the trigger families
(``rlbackdoors/triggers/``) and every module the registry points at (env classes, batched
engines, architectures, benchmarks) plus its siblings of the same stem (``envs/lavaworld*.py``).
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

from rlbackdoors import worlds

SRC = Path(__file__).parents[1] / "src" / "rlbackdoors"


def _module_file(path: str) -> Path:
    return SRC.parent / (path.partition(":")[0].replace(".", "/") + ".py")


def world_modules() -> set[Path]:
    """Files allowed to name a world: the registry, trigger families, and the registry's targets' stems."""
    stems = set()
    for w in worlds.registered():
        targets = [w.entry_point, w.vector_entry_point, w.bench, *(path for _, path in w.archs)]
        stems |= {_module_file(t).with_suffix("").name.split("_batched")[0].split("_bench")[0] for t in targets if t}
    allowed = set((SRC / "worlds").glob("*.py")) | set((SRC / "triggers").glob("*.py"))
    for sub in ("envs", "models", "bench"):
        allowed |= {p for p in (SRC / sub).glob("*.py") if any(p.stem.startswith(stem) for stem in stems)}
    return allowed


def world_patterns() -> re.Pattern:
    words = set()
    for w in worlds.registered():
        words |= {w.name, w.name.replace("-", "_"), w.title, w.title.replace(" ", ""), w.entry_point.rpartition(":")[2]}
        words.add(w.entry_point.partition(":")[0].rpartition(".")[2])  # the env module's name
    return re.compile("|".join(sorted(map(re.escape, words), key=len, reverse=True)), re.IGNORECASE)


def test_no_world_is_named_outside_its_modules():
    allowed, pattern = world_modules(), world_patterns()
    assert len(allowed) > 10 and pattern.search("the LavaWorld env") and pattern.search("safety_car")
    hits = []
    for path in sorted(SRC.rglob("*.py")):
        if path in allowed:
            continue
        for number, line in enumerate(path.read_text().splitlines(), 1):
            if pattern.search(line):
                hits.append(f"{path.relative_to(SRC)}:{number}: {line.strip()}")
    assert not hits, "world names outside world modules:\n" + "\n".join(hits)


def _imports(path: Path) -> set[str]:
    """Every rlbackdoors module ``path`` imports, at the top or inside functions."""
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("rlbackdoors"):
            found.add(node.module)
            found |= {f"{node.module}.{a.name}" for a in node.names}
        elif isinstance(node, ast.Import):
            found |= {a.name for a in node.names if a.name.startswith("rlbackdoors")}
    return found


def _package(module: str) -> str:
    """The sub-package a module belongs to (top-level modules are their own)."""
    parts = module.split(".")
    return ".".join(parts[:2])


def test_no_package_import_cycle():
    modules = {".".join(p.relative_to(SRC.parent).with_suffix("").parts).removesuffix(".__init__"): p for p in SRC.rglob("*.py")}
    graph: dict[str, set[str]] = {}
    for name, path in modules.items():
        targets = {_package(m) for m in _imports(path) if m in modules or m.rpartition(".")[0] in modules}
        graph.setdefault(_package(name), set()).update(t for t in targets if t != _package(name) and t != "rlbackdoors")
    assert "rlbackdoors.train" in graph and "rlbackdoors.config" in graph["rlbackdoors.train"]

    cycles = []

    def visit(node: str, stack: list[str]) -> None:
        for nxt in sorted(graph.get(node, ())):
            if nxt in stack:
                cycles.append(" -> ".join(stack[stack.index(nxt) :] + [nxt]))
            elif len(stack) < 12:
                visit(nxt, stack + [nxt])

    for start in sorted(graph):
        visit(start, [start])
    assert not cycles, "package import cycles:\n" + "\n".join(sorted(set(cycles))[:20])


def test_the_trainers_modules_import_each_other_in_no_circle():
    """Issue 78: the compiled trainer is one room (``algos/compiled.py``), what it shares with the
    rest is below it (``algos/xla.py``, ``algos/stacked.py``), and no module of ``rlbackdoors.algos``
    reaches itself through its imports, lazy ones in function bodies included (the JAX update was
    once imported by the torch group and PPO, and imported them back)."""
    modules = {".".join(p.relative_to(SRC.parent).with_suffix("").parts).removesuffix(".__init__"): p for p in SRC.rglob("*.py")}
    algos = {name: path for name, path in modules.items() if name.startswith("rlbackdoors.algos.")}
    graph = {name: {m for m in _imports(path) if m in algos and m != name} for name, path in algos.items()}
    assert "rlbackdoors.algos.xla" in graph["rlbackdoors.algos.compiled"] and "rlbackdoors.algos.compiled" in graph["rlbackdoors.algos.group"]
    cycles = []

    def visit(node: str, stack: list[str]) -> None:
        for nxt in sorted(graph[node]):
            if nxt in stack:
                cycles.append(" -> ".join(stack[stack.index(nxt) :] + [nxt]))
            else:
                visit(nxt, stack + [nxt])

    for start in sorted(graph):
        visit(start, [start])
    assert not cycles, "module import cycles in rlbackdoors.algos:\n" + "\n".join(sorted(set(cycles)))
    assert not (SRC / "algos" / "jax_update.py").exists()


def test_no_attack_is_named_outside_its_modules():
    """Issue 33: an attack is one module of ``rlbackdoors/attacks/``; config, algorithms, evaluation
    and zoos ask the registry (the default, the paper's env mix, by ``attacks.DEFAULT_ATTACK``)."""
    from rlbackdoors import attacks

    words = set()
    for attack in attacks.registered():
        words |= {attack.name, attack.title, attack.title.replace(" ", "")}
    pattern = re.compile(r"\b(" + "|".join(sorted(map(re.escape, words), key=len, reverse=True)) + r")\b", re.IGNORECASE)
    assert pattern.search("a TrojDRL agent") and pattern.search("attack = 'envmix'")
    hits = []
    for path in sorted(SRC.rglob("*.py")):
        if (SRC / "attacks") in path.parents:
            continue
        for number, line in enumerate(path.read_text().splitlines(), 1):
            if pattern.search(line):
                hits.append(f"{path.relative_to(SRC)}:{number}: {line.strip()}")
    assert not hits, "attack names outside rlbackdoors/attacks/:\n" + "\n".join(hits)
