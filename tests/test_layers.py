"""The package layers of cell/ (docs/architecture.md): a package imports only from packages
below it, kernels/ from nothing of ours, sim/ only from cell's layers up to planning, and only
cell.run.backends reaches sim/ and the real adapters (cell.devices.hw). No import circles.
Imports are read as text, those inside functions too, so a late import cannot hide a crossing."""
import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent

# bottom to top; a package may import its own modules and those of any package listed before it
LAYERS = ("core", "physics", "task", "devices", "collision", "planning", "report", "run", "calibration", "bench", "cli")
BUILDS_DEVICES = "cell.run.backends"
SIM_SEES_UP_TO = "planning"


def module_files():
    out = {}
    for top in ("cell", "kernels", "sim"):
        for path in (ROOT / top).rglob("*.py"):
            parts = list(path.relative_to(ROOT).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts = parts[:-1]
            out[".".join(parts)] = path
    return out


def import_graph():
    """module -> the project modules it imports (a name resolved to its longest module prefix)."""
    files = module_files()

    def resolve(name):
        while name and name not in files:
            name = name.rpartition(".")[0]
        return name

    graph = {}
    for module, path in files.items():
        found = set()
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                names = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names = [node.module] + [f"{node.module}.{alias.name}" for alias in node.names]
            else:
                continue
            found |= {r for r in map(resolve, names) if r and r != module}
        graph[module] = found
    return graph


def layer(module):
    """The layer index of a cell module, None for cell's own __init__ and __main__."""
    parts = module.split(".")
    if parts[0] != "cell" or len(parts) < 2 or parts[1] not in LAYERS:
        return None
    return LAYERS.index(parts[1])


def crossings(graph):
    bad = []
    for module, imports in graph.items():
        for target in imports:
            top = target.split(".")[0]
            if module.startswith("kernels"):
                if top != "kernels":
                    bad.append((module, target, "kernels/ imports nothing of cell/ or sim/"))
                continue
            reaches_devices = top == "sim" or target.startswith("cell.devices.hw")
            if reaches_devices and module != BUILDS_DEVICES and not module.startswith(("sim", "cell.devices.hw")):
                bad.append((module, target, f"only {BUILDS_DEVICES} builds devices"))
                continue
            if module.startswith("sim"):
                if target.startswith("cell.devices.hw") or (
                        layer(target) is not None and layer(target) > LAYERS.index(SIM_SEES_UP_TO)):
                    bad.append((module, target, f"sim/ sees cell only up to cell.{SIM_SEES_UP_TO}"))
                continue
            if module.startswith("cell") and top == "cell":
                mine, theirs = layer(module), layer(target)
                if mine is not None and theirs is not None and theirs > mine:
                    bad.append((module, target, f"cell.{LAYERS[theirs]} is above cell.{LAYERS[mine]}"))
    return sorted(bad)


def circles(graph):
    """Strongly connected components of more than one module (Tarjan, iteratively)."""
    index, low, on_stack, stack, found, counter = {}, {}, set(), [], [], [0]
    for root in graph:
        if root in index:
            continue
        work = [(root, iter(sorted(graph.get(root, ()))))]
        index[root] = low[root] = counter[0]
        counter[0] += 1
        stack.append(root)
        on_stack.add(root)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = counter[0]
                    counter[0] += 1
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
                    member = stack.pop()
                    on_stack.discard(member)
                    component.append(member)
                    if member == node:
                        break
                if len(component) > 1:
                    found.append(sorted(component))
    return found


def test_every_cell_module_lies_in_a_layer():
    loose = [m for m in module_files() if m.startswith("cell.") and layer(m) is None
             and m not in ("cell.__main__",)]
    assert loose == [], f"modules outside the layer packages: {loose}"


def test_no_package_imports_from_above():
    assert crossings(import_graph()) == []


def test_no_import_circles():
    assert circles(import_graph()) == []


def test_the_checks_see_a_crossing_and_a_circle():
    """The checks can fail: a planning module importing the run, and two modules importing
    each other, are found."""
    graph = {"cell.planning.scene": {"cell.run.loop"}, "cell.run.loop": {"cell.planning.scene"},
             "kernels.mesh": {"cell.core.errors"}, "cell.planning.one_shot": {"sim.world"}}
    reasons = [why for _, _, why in crossings(graph)]
    assert "cell.run is above cell.planning" in reasons
    assert "kernels/ imports nothing of cell/ or sim/" in reasons
    assert f"only {BUILDS_DEVICES} builds devices" in reasons
    assert circles(graph) == [["cell.planning.scene", "cell.run.loop"]]
