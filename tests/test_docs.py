"""The README and docs/ name only what exists: every relative link (and its #anchor), every repository path in
backticks, every ``python -m nsl_hpc.<command>``."""

import importlib.util
import re
from pathlib import Path

import pytest
from omegaconf import OmegaConf

from nsl_hpc.analysis.published import published_laws
from nsl_hpc.analysis.reproduction import (
    BEGIN,
    FIGURES_BEGIN,
    FIGURES_END,
    figure_name,
    figures_block,
    read_statuses,
    status_table,
    table_in,
)

ROOT = Path(__file__).resolve().parents[1]
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
TOP = {"nsl_hpc", "conf", "tests", "benchmarks", "jobs", "cluster", "docs", ".ci"}
PACKAGES = {path.name for path in (ROOT / "nsl_hpc").iterdir() if path.is_dir() and not path.name.startswith("_")}
LINK = re.compile(r"\]\(([^)\s]+)\)")
CODE = re.compile(r"`([^`\s]+)`")
PATHLIKE = re.compile(r"[\w.-]+(/[\w.-]+)*/?")
SITE_FILES = {"conf/local/default.yaml"}  # git-ignored: a site writes it (launcher.partition, ...)


def slug(heading: str) -> str:
    """GitHub's anchor of a Markdown heading."""
    text = re.sub(r"[^\w\- ]", "", heading.lstrip("#").strip().lower())
    return text.replace(" ", "-")


def anchors(path: Path) -> set[str]:
    return {slug(line) for line in path.read_text().splitlines() if line.startswith("#")}


def repository_path(token: str) -> Path | None:
    """Where a backticked token that names a file of this repository should be (None: not such a token)."""
    token = token.rstrip(".,:;")
    if not PATHLIKE.fullmatch(token) or "/" not in token or token in SITE_FILES:
        return None
    first = token.split("/", 1)[0]
    if first in TOP:
        return ROOT / token
    if first in PACKAGES:
        return ROOT / "nsl_hpc" / token
    return None


@pytest.mark.parametrize("doc", DOCS, ids=lambda path: path.name)
def test_every_link_of_a_doc_leads_somewhere(doc):
    for target in LINK.findall(doc.read_text()):
        if re.match(r"[a-z]+:", target):
            continue  # a web address
        file, _, anchor = target.partition("#")
        path = (doc.parent / file).resolve() if file else doc
        assert path.exists(), f"{doc.name} links to {target}, which does not exist"
        if anchor and path.suffix == ".md":
            assert anchor in anchors(path), f"{doc.name} links to {target}: no such heading"


@pytest.mark.parametrize("doc", DOCS, ids=lambda path: path.name)
def test_every_repository_path_a_doc_names_exists(doc):
    missing = [token for token in CODE.findall(doc.read_text())
               if (path := repository_path(token)) is not None and not path.exists()]
    assert not missing, f"{doc.name} names paths that do not exist: {missing}"


@pytest.mark.parametrize("doc", DOCS, ids=lambda path: path.name)
def test_every_command_a_doc_names_runs(doc):
    for module in set(re.findall(r"python -m (nsl_hpc(?:\.\w+)+)", doc.read_text())):
        spec = importlib.util.find_spec(module)
        assert spec is not None, f"{doc.name} names python -m {module}, which does not exist"
        if spec.submodule_search_locations:
            spec = importlib.util.find_spec(f"{module}.__main__")
            assert spec is not None, f"{doc.name} names python -m {module}, a package without __main__"
        assert 'if __name__ == "__main__":' in Path(spec.origin).read_text(), f"{module} is no command"


def test_the_checker_resolves_paths_and_anchors_as_github_does():
    assert repository_path("nsl_hpc/no_such_module.py") is not None
    assert not repository_path("nsl_hpc/no_such_module.py").exists()
    assert repository_path("sweep/plan.py") == ROOT / "nsl_hpc" / "sweep" / "plan.py"
    assert repository_path("runs/demo/report.html") is None  # an output, not a file of the repository
    assert slug("### Reading a fit: the published laws") == "reading-a-fit-the-published-laws"


FIGURE = re.compile(r"(?<![\w.])\d+(?:\.\d+)?e[+-]?\d+|(?<![\w.])\d+\.\d+")  # 0.95, 2.2e6: a quoted figure
NOT_FIGURES = re.compile(r"`[^`]*`|Section \d+(?:\.\d+)*|arXiv:\S+")  # code, settings and places in the paper
DATE = re.compile(r"\b20\d\d-\d\d-\d\d\b")
OUTPUT = re.compile(r"docs/reproduction/[\w.-]+\.md")  # a committed copy of a command's output


def quoted_figures(text: str) -> list[str]:
    return FIGURE.findall(NOT_FIGURES.sub(" ", text))


def measurement_units() -> list[tuple[str, str]]:
    """(where, text) of each place that quotes measured figures: the Fidelity table's last column (the
    alternatives and the evidence, docs/fidelity.md), and docs/reproduction.md's summary (its "In short"
    paragraphs)."""
    fidelity = (ROOT / "docs" / "fidelity.md").read_text()
    units = [(f"docs/fidelity.md, {cells[0].strip()}", cells[-1])
             for cells in (line.strip("|").split(" | ") for line in fidelity.splitlines()
                           if line.startswith("| ") and not line.startswith(("| choice", "|---")))]
    reproduction = (ROOT / "docs" / "reproduction.md").read_text()
    summary = reproduction.split("**In short", 1)[1].split("\n## ", 1)[0]
    return units + [(f"docs/reproduction.md summary, paragraph {i}", paragraph)
                    for i, paragraph in enumerate(summary.split("\n\n"))]


@pytest.mark.parametrize(("where", "text"), measurement_units(), ids=[where for where, _ in measurement_units()])
def test_every_quoted_figure_is_dated_or_in_the_output_it_names(where, text):
    """A measured figure in the Fidelity table or the reproduction summary is either dated (the run's
    date in the same cell or paragraph) or appears verbatim in the committed command output it names."""
    figures = quoted_figures(text)
    if not figures or DATE.search(text):
        return
    outputs = OUTPUT.findall(text)
    assert outputs, f"{where}: quotes {figures[:4]} with neither a date nor the output (docs/reproduction/*.md)"
    produced = " ".join((ROOT / output).read_text() for output in outputs)
    missing = [figure for figure in figures if figure not in produced]
    assert not missing, f"{where}: {missing} are not in {', '.join(outputs)}"


def test_the_figure_finder_skips_code_settings_and_places_in_the_paper():
    assert quoted_figures("0.95-1.83x at 2.2e6 flops, `train.lr=2.0e-3`, Section 4.3, 1,106 steps") == [
        "0.95", "1.83", "2.2e6"]


def test_the_reproduction_status_table_is_the_one_its_committed_numbers_give():
    """docs/reproduction.md opens with the table ``benchmarks/reproduction_status.py`` writes from the committed
    docs/reproduction/status.json: regenerated here, it must be the document's, and it covers every published law."""
    cfg = OmegaConf.load(ROOT / "conf" / "reproduction.yaml")
    statuses = read_statuses(ROOT / cfg.status)
    assert sorted(cfg.laws) == sorted("/".join(key) for key in published_laws())
    expected = status_table([statuses[law] for law in cfg.laws], cfg.within)
    document = (ROOT / cfg.document).read_text()
    assert table_in(document) == expected, "run python benchmarks/reproduction_status.py collect=false"
    assert document.index(BEGIN) < document.index("\n## ")  # the table comes before the first section
    folder = ROOT / cfg.comparisons
    present = sorted(path.name for path in folder.glob("*.png"))
    assert set(present) <= {figure_name(law) for law in cfg.laws}  # figures of published laws only
    shown = table_in(document, FIGURES_BEGIN, FIGURES_END)
    assert shown == figures_block([statuses[law] for law in cfg.laws], "reproduction", present)


def layout_tree() -> dict[Path, set[str]]:
    """docs/layout.md's tree of nsl_hpc: folder -> the module names (in backticks) its paragraph lists."""
    tree = (ROOT / "docs" / "layout.md").read_text().split("```")[1]
    block = tree[tree.index("\nnsl_hpc/") + 1:tree.index("\njobs/")]
    listed: dict[Path, set[str]] = {}
    parents: list[str] = []
    for line in block.splitlines():
        if match := re.match(r"( *)([a-z_]+)/ ", line):  # a folder's paragraph begins
            depth = len(match.group(1)) // 2
            parents = [*parents[:depth], match.group(2)]
            folder = ROOT.joinpath(*parents)
        listed.setdefault(folder, set()).update(re.findall(r"`([A-Za-z_]+)`", line))
    return listed


def test_the_layout_lists_every_module_and_only_modules_that_exist():
    listed = layout_tree()
    packages = {path.parent for path in (ROOT / "nsl_hpc").rglob("__init__.py")}
    assert set(listed) == packages
    for folder, names in listed.items():
        modules = {path.stem for path in folder.glob("*.py")}
        assert names <= modules, f"{folder}: {sorted(names - modules)} listed but not there"
        assert modules - {"__init__"} <= names, f"{folder}: {sorted(modules - {'__init__'} - names)} not listed"


def test_the_top_level_shows_the_commands():
    """Directly under nsl_hpc/ sit the commands (each runs as ``python -m nsl_hpc.<verb>``) and what users and the
    commands share at their level (cli, registry, the public fit API): no more than 20 modules; the shared base
    is core/."""
    top = {path.stem: path.read_text() for path in (ROOT / "nsl_hpc").glob("*.py") if path.stem != "__init__"}
    commands = {name for name, source in top.items() if 'if __name__ == "__main__":' in source}
    assert set(top) - commands == {"cli", "registry", "nsl"}
    assert len(top) <= 20


def test_the_glossary_names_definitions_the_code_has():
    """Each term of docs/layout.md's glossary points at a definition (class, function or attribute) by its module:
    the names a reader meets in the code."""
    glossary = (ROOT / "docs" / "layout.md").read_text().split("## Glossary", 1)[1]
    references = re.findall(r"`([\w/]+\.py): ([\w.]+)`", glossary)
    assert len(references) >= 20
    for module, name in references:
        source = (ROOT / "nsl_hpc" / module).read_text()
        first, _, attribute = name.partition(".")
        assert re.search(rf"^(class|def) {first}\b", source, re.MULTILINE), f"{module} defines no {first}"
        if attribute:
            assert re.search(rf"^    {attribute}\b", source, re.MULTILINE), f"{module}: {first} has no {attribute}"
