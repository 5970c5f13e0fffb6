"""Types at the boundaries: mypy passes on the project ([tool.mypy] in pyproject.toml), and every
public function, method and dataclass field of the typed packages carries its annotations (mypy
checks a function only when it is annotated, so an unannotated one would pass unseen)."""
import ast
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent

# the packages whose public functions, methods and dataclass fields must be annotated
TYPED_PACKAGES = ("cell.core", "cell.physics", "cell.task", "cell.devices", "cell.planning", "cell.report",
                  "cell.run", "cell.calibration", "cell.bench",
                  "cell.cli", "sim", "kernels")
# Warp's @wp.func and @wp.kernel are typed in Warp's kernel language, which Warp checks (a kernel
# returns nothing and says so by no annotation)
WARP_DECORATORS = ("wp.func", "wp.kernel")
# a field typed so says nothing: its real type belongs in the annotation
VAGUE_FIELD_TYPES = ("object", "Any", "typing.Any")


def test_mypy_passes():
    """`python -m mypy` on cell, kernels and sim reports no error (its output is the message)."""
    pytest.importorskip("mypy")
    run = subprocess.run([sys.executable, "-m", "mypy", "--cache-dir", str(ROOT / ".mypy_cache")],
                         cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stdout + run.stderr


def package_files(package):
    folder = ROOT.joinpath(*package.split("."))
    return sorted(folder.rglob("*.py"))


def decorated(node, names):
    """Whether a decorator of node is one of names, called (`@dataclass(frozen=True)`) or not."""
    return any(ast.unparse(d.func if isinstance(d, ast.Call) else d) in names for d in node.decorator_list)


def unannotated(function, is_method):
    """The parameters of a function (self or cls of a method aside) that lack an annotation, and
    "return" when the return type is missing."""
    args = function.args
    params = args.posonlyargs + args.args + args.kwonlyargs
    if is_method and params and params[0].arg in ("self", "cls") and not any(
            ast.unparse(d) == "staticmethod" for d in function.decorator_list):
        params = params[1:]
    params += [p for p in (args.vararg, args.kwarg) if p is not None]
    missing = [p.arg for p in params if p.annotation is None]
    if function.returns is None and function.name != "__init__":
        missing.append("return")
    return missing


def annotation_gaps(path, root=ROOT):
    """Each gap as "file:line name: what is missing": a public function or method (its name without
    a leading underscore, or __init__) lacking an annotation, a dataclass field typed vaguely."""
    gaps = []
    where = path.relative_to(root)

    def visit(body, owner):
        for node in body:
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                if (node.name.startswith("_") and node.name != "__init__") or decorated(node, WARP_DECORATORS):
                    continue
                missing = unannotated(node, owner is not None)
                if missing:
                    qualified = f"{owner}.{node.name}" if owner else node.name
                    gaps.append(f"{where}:{node.lineno} {qualified}: {', '.join(missing)}")
            elif isinstance(node, ast.ClassDef):
                name = f"{owner}.{node.name}" if owner else node.name
                if decorated(node, ("dataclass", "dataclasses.dataclass")):
                    for item in node.body:
                        if isinstance(item, ast.Assign):      # not a field: a class attribute
                            gaps.append(f"{where}:{item.lineno} {name}: an attribute without a type "
                                        "(a field needs one, a constant says ClassVar)")
                        elif (isinstance(item, ast.AnnAssign)
                              and ast.unparse(item.annotation) in VAGUE_FIELD_TYPES):
                            gaps.append(f"{where}:{item.lineno} {name}.{ast.unparse(item.target)}: "
                                        f"typed {ast.unparse(item.annotation)}")
                visit(node.body, name)

    visit(ast.parse(path.read_text()).body, None)
    return gaps


@pytest.mark.parametrize("package", TYPED_PACKAGES)
def test_public_functions_and_fields_are_annotated(package):
    files = package_files(package)
    assert files, f"no modules found for {package}"
    gaps = [gap for path in files for gap in annotation_gaps(path)]
    assert not gaps, "missing annotations:\n" + "\n".join(gaps)


def test_the_annotation_check_sees_a_gap(tmp_path):
    """The AST check flags what it should, so a pass above means the annotations are there."""
    source = tmp_path / "sample.py"
    source.write_text(
        "from dataclasses import dataclass\n"
        "def typed(x: int) -> int: ...\n"
        "def _private(x): ...\n"
        "def untyped(x, *rest, y: int = 0): ...\n"
        "class Thing:\n"
        "    def method(self, a: int): ...\n"
        "    @staticmethod\n"
        "    def static(self) -> None: ...\n"
        "@wp.kernel\n"
        "def launched(a: wp.array(dtype=float)): ...\n"
        "@dataclass\n"
        "class Fields:\n"
        "    good: int\n"
        "    vague: object = None\n"
        "    loose = 0\n")
    gaps = [gap.split(" ", 1)[1] for gap in annotation_gaps(source, tmp_path)]
    assert gaps == ["untyped: x, rest, return", "Thing.method: return", "Thing.static: self",
                    "Fields.vague: typed object",
                    "Fields: an attribute without a type (a field needs one, a constant says ClassVar)"]

