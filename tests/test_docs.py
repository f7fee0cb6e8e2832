"""The README and docs/ name only what exists: every relative link (and its #anchor), every repository path in
backticks, every ``python -m nsl_hpc.<command>``."""

import importlib.util
import re
from pathlib import Path

import pytest

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
