"""The docs describe the repository as it is: docs/architecture.md's module map lists every module
of cell/ by package and names none that does not exist; README.md links every docs page; every
relative link (and its #anchor) and every backticked path into the repository's own folders names
a file or folder that a clone has; README.md starts with its title and the two commands a newcomer
runs, the second the one CI runs, and stays short."""
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
README = ROOT / "README.md"
DOCS = sorted((ROOT / "docs").glob("*.md"))
PAGES = [README, *DOCS]
REPOSITORY_FOLDERS = ("cell", "kernels", "sim", "tasks", "tests", "docs", ".ci")
FIRST_COMMAND = "python3 -m venv .venv && . .venv/bin/activate && pip install -e . && cell run tasks/hinge.yaml"
TEST_COMMAND = "python3 -m venv .venv && . .venv/bin/activate && pip install -e '.[test]' && pytest -q"
README_MAX_LINES = 320

FENCED = re.compile(r"^```.*?^```", re.S | re.M)
INLINE_CODE = re.compile(r"`([^`\n]+)`")
LINK = re.compile(r"\[[^\]]*\]\(([^)\s]+)\)")
REPOSITORY_PATH = re.compile(
    r"(?<![\w./-])((?:%s)/[^\s`'\"<>(),;:]*)" % "|".join(re.escape(f) for f in REPOSITORY_FOLDERS))


def module_map():
    """{package folder: its module names} from the `## Module map` table of docs/architecture.md:
    each row's first cell a backticked `cell/.../` folder, its second the backticked modules."""
    text = (ROOT / "docs" / "architecture.md").read_text()
    section = text[text.index("\n## Module map"):]
    section = section[:section.find("\n## ", 1) if "\n## " in section[1:] else None]
    documented = {}
    for line in section.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if line.startswith("| `cell") and len(cells) >= 2:
            package = cells[0].strip("`")
            assert package not in documented, f"{package} has two rows"
            documented[package] = set(INLINE_CODE.findall(cells[1]))
    return documented


def code_modules():
    """{package folder: its module names} of every folder of cell/ holding Python files."""
    found = {}
    for path in (ROOT / "cell").rglob("*.py"):
        package = path.parent.relative_to(ROOT).as_posix() + "/"
        found.setdefault(package, set())
        if path.stem != "__init__":
            found[package].add(path.stem)
    return found


def test_the_module_map_lists_every_module_of_cell_and_no_other():
    documented, actual = module_map(), code_modules()
    missing = sorted(f"{p}{m}.py" for p, mods in actual.items() for m in mods - documented.get(p, set()))
    absent = sorted(f"{p}{m}.py" for p, mods in documented.items() for m in mods - actual.get(p, set()))
    assert missing == [], "modules of cell/ not in docs/architecture.md's module map"
    assert absent == [], "docs/architecture.md's module map names modules that do not exist"
    assert sorted(documented) == sorted(actual)


def test_every_docs_page_is_linked_from_the_readme():
    linked = {(ROOT / target.partition("#")[0]).resolve() for target in LINK.findall(README.read_text())}
    assert [page.name for page in DOCS if page.resolve() not in linked] == []


def slug(heading):
    """GitHub's anchor of a heading: lower case, punctuation but - and _ dropped, spaces to -."""
    return re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")


def anchors(page):
    seen, out = {}, set()
    for heading in re.findall(r"^#+ (.*)$", FENCED.sub("", page.read_text()), re.M):
        name = slug(heading)
        out.add(f"{name}-{seen[name]}" if name in seen else name)
        seen[name] = seen.get(name, 0) + 1
    return out


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.name)
def test_every_relative_link_names_a_file_and_heading_that_exist(page):
    broken = []
    for target in LINK.findall(page.read_text()):
        if re.match(r"[a-z]+:", target):
            continue                                     # http:, https:, mailto: are not the clone's
        path, _, anchor = target.partition("#")
        file = (page.parent / path).resolve() if path else page
        if not file.exists() or (anchor and file.suffix == ".md" and anchor not in anchors(file)):
            broken.append(target)
    assert broken == []


def repository_paths(text):
    """The paths into the repository's own folders named in `code` and in fenced blocks."""
    spans = INLINE_CODE.findall(FENCED.sub("", text)) + FENCED.findall(text)
    return {path.rstrip(".") for span in spans for path in REPOSITORY_PATH.findall(span)}


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.name)
def test_every_backticked_repository_path_exists(page):
    missing = sorted(p for p in repository_paths(page.read_text())
                     if not (list(ROOT.glob(p)) if "*" in p else (ROOT / p).exists()))
    assert missing == []


def test_the_path_check_sees_a_path_that_does_not_exist():
    found = repository_paths("see `cell/run/loop.py` and `cell/devices/hw.py`, not `runs/x/plan.json`\n"
                             "```\n$ cell plan tasks/nowhere.yaml\n  wrote runs/a/plan.json\n```\n")
    assert found == {"cell/run/loop.py", "cell/devices/hw.py", "tasks/nowhere.yaml"}
    assert not (ROOT / "cell/devices/hw.py").exists() and (ROOT / "cell/run/loop.py").exists()


def test_the_readme_opens_with_its_title_and_the_two_commands_and_is_short():
    lines = README.read_text().splitlines()
    assert len(lines) <= README_MAX_LINES
    title, *rest = [line for line in lines[:8] if line.strip()]
    assert title.startswith("# ")
    assert [line.strip() for line in rest[:2]] == [FIRST_COMMAND, TEST_COMMAND]
    assert all(line.startswith("    ") for line in rest[:2])       # each a code line of its own


def test_ci_runs_the_readme_s_test_command():
    ci = (ROOT / ".ci" / "run").read_text()
    assert TEST_COMMAND.partition("activate && ")[2] in ci


# a figure of time a person could take for a promise: a duration beside a word of measuring
MEASURED_TIME = re.compile(r"\b(took|takes|take|planned in|in all)\b[^.]*?\b\d+(\.\d+)? ?(s|min|minutes)\b"
                           r"|\b\d+:\d\d\b[^.]*\b(fresh clone|run)\b")


def timed_paragraphs(text):
    """The prose paragraphs of a page (neither code blocks nor tables) that state a time measured."""
    prose = FENCED.sub("", text)
    return [p for p in prose.split("\n\n") if not p.lstrip().startswith("|") and MEASURED_TIME.search(p)]


def test_every_time_the_readme_states_says_on_what_machine_and_at_what_load():
    """Issue 29, item 8: `cell bench --quick` was 'about 20 s' in the README and took 67 s on a
    loaded machine: every time measured that the README states names the machine and the load
    (or that it was idle, or that the load was not recorded)."""
    assert timed_paragraphs("The bench takes about 20 s.\n\nA shutter of 20 s.\n") == ["The bench takes about 20 s."]
    paragraphs = timed_paragraphs(README.read_text())
    assert paragraphs                                     # the README does state times
    for paragraph in paragraphs:
        assert re.search(r"\bload\b|\bidle\b", paragraph) and re.search(r"machine|EPYC|core", paragraph), paragraph
