"""The documentation's links and paths exist: every relative Markdown link or image of README.md,
docs/ and experiments/, and every ``docs/...``, ``experiments/...`` or ``benchmarks/...`` path those
files name, points to a file or folder of the repository, so a moved file cannot leave a dangling
reference behind."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]

#: The Markdown files checked: the README, the maintained docs and the experiments' write-ups.
DOCS = sorted([REPO / "README.md", *(REPO / "docs").rglob("*.md"), *(REPO / "experiments").rglob("*.md")])

#: ``[text](target)`` and ``![alt](target)``; the target up to a space (a title may follow) or ``)``.
LINK = re.compile(r"!?\[[^\]]*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")
#: A repository path in prose or code: ``docs/...``, ``experiments/...`` or ``benchmarks/...``, not
#: part of a longer path (``../shared/docs/x`` is not one), ending in a word character; ``{a,b}``
#: alternatives and ``*`` patterns allowed.
REPO_PATH = re.compile(r"(?<![\w./-])((?:docs|experiments|benchmarks)/(?:[\w./*-]|\{[\w.,-]+\})*\w)")
BRACES = re.compile(r"\{([^{}]*)\}")


def _exists(path: Path) -> bool:
    """``path`` exists; each alternative of a ``{a,b}`` in it, and at least one match of a ``*``."""
    braces = BRACES.search(str(path))
    if braces:
        return all(_exists(Path(str(path)[:braces.start()] + alt + str(path)[braces.end():]))
                   for alt in braces.group(1).split(","))
    if "*" in path.name:
        return any(path.parent.glob(path.name))
    return path.exists()


def _links(doc: Path) -> list[tuple[int, str]]:
    found = []
    for number, line in enumerate(doc.read_text().splitlines(), 1):
        for target in LINK.findall(line):
            if re.match(r"^[a-z][a-z0-9+.-]*:", target, re.I) or target.startswith("#"):
                continue  # a URL (https:, mailto:) or an anchor in the same file
            found.append((number, target.split("#")[0]))
    return found


def _repo_paths(doc: Path) -> list[tuple[int, str]]:
    return [(number, p) for number, line in enumerate(doc.read_text().splitlines(), 1)
            for p in REPO_PATH.findall(line)]


def test_the_documents_are_there():
    names = {d.relative_to(REPO).as_posix() for d in DOCS}
    assert {"README.md", "docs/results.md", "docs/conventions.md", "experiments/README.md"} <= names


@pytest.mark.parametrize("doc", DOCS, ids=lambda d: d.relative_to(REPO).as_posix())
def test_relative_links_resolve(doc):
    """A link is relative to the file that holds it, as GitHub and every Markdown viewer read it."""
    broken = [f"{doc.relative_to(REPO)}:{n}: {t}" for n, t in _links(doc) if not _exists(doc.parent / t)]
    assert not broken, "dangling links:\n" + "\n".join(broken)


@pytest.mark.parametrize("doc", DOCS, ids=lambda d: d.relative_to(REPO).as_posix())
def test_named_repository_paths_exist(doc):
    """``docs/x.md`` in running text names the file from the repository's root."""
    missing = [f"{doc.relative_to(REPO)}:{n}: {p}" for n, p in _repo_paths(doc) if not _exists(REPO / p)]
    assert not missing, "paths that are not in the repository:\n" + "\n".join(missing)


def test_the_checks_catch_a_broken_reference(tmp_path):
    """The patterns find what they must (so the tests above cannot pass by matching nothing)."""
    doc = tmp_path / "x.md"
    doc.write_text("![a](docs/nowhere.png) see [b](other.md#part), `docs/gone.md`, benchmarks/none.py.\n"
                   "[web](https://example.org/docs/x) ../shared/docs/y.md [here](#top) docs/slicer_{pa,lat}_{x,after}.png\n")
    assert _links(doc) == [(1, "docs/nowhere.png"), (1, "other.md")]
    assert _repo_paths(doc) == [(1, "docs/nowhere.png"), (1, "docs/gone.md"), (1, "benchmarks/none.py"),
                                (2, "docs/slicer_{pa,lat}_{x,after}.png")]
    assert not _exists(tmp_path / "other.md") and not _exists(REPO / "docs/slicer_{pa,lat}_{x,after}.png")
    assert _exists(REPO / "docs/slicer_{pa,lat}_{before,after}.png") and _exists(REPO / "Testing/Python/test_doc_*.py")
