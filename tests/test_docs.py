"""The documentation names only what the repository has: every relative link in the Markdown files resolves, every
repository path written in code quotes (`docs/...`, `efem_viz/...`, ...) exists, and every `docs/....md` the code's
docstrings and help texts cite is there (a user has the repository, not the team's design folder)."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
TOP = ("docs", "efem_viz", "annotator", "bench", "scripts", "tests", "examples", "sample_scenes")


def _markdown() -> list[Path]:
    files = [ROOT / "README.md", ROOT / "CHANGELOG.md", *ROOT.glob("docs/**/*.md"), *ROOT.glob("examples/**/*.md"),
             *ROOT.glob("efem_viz/**/*.md"), *ROOT.glob("sample_scenes/*.md")]
    assert len(files) > 10
    return files


def test_every_relative_link_resolves() -> None:
    broken = []
    for f in _markdown():
        for m in re.finditer(r"\]\(([^)\s]+)\)", f.read_text(encoding="utf-8")):
            target = m.group(1)
            if re.match(r"^[a-z][a-z0-9+.-]*:", target) or target.startswith("#"):
                continue  # a web address or an anchor in the same page
            if not (f.parent / target.split("#")[0]).exists():
                broken.append(f"{f.relative_to(ROOT)}: {target}")
    assert not broken, broken


def test_every_quoted_repository_path_exists() -> None:
    """Paths in code quotes that start at a top-level folder; placeholders (`<scene>`, `*`, `{x}`, `DIR`) and the
    copied design notes (the team's conventions, e.g. where golden files would go) are not checked."""
    missing = []
    pattern = re.compile(r"`((?:" + "|".join(TOP) + r")/[A-Za-z0-9_./-]+)`")
    for f in _markdown():
        if f.is_relative_to(ROOT / "docs" / "design"):
            continue
        for m in pattern.finditer(f.read_text(encoding="utf-8")):
            path = m.group(1).rstrip(".")
            if re.search(r"[<>*{}\[\]]|[A-Z]{2,}", path):
                continue
            if not (ROOT / path).exists():
                missing.append(f"{f.relative_to(ROOT)}: {path}")
    assert not missing, missing


def test_the_code_cites_documents_that_ship() -> None:
    missing = []
    for f in [*ROOT.glob("efem_viz/**/*.py"), *ROOT.glob("annotator/**/*.py")]:
        text = f.read_text(encoding="utf-8")
        for m in re.finditer(r"\b(docs/[A-Za-z0-9_./-]+\.md)\b", text):
            if not (ROOT / m.group(1)).exists():
                missing.append(f"{f.relative_to(ROOT)}: {m.group(1)}")
        for m in re.finditer(r"(?<![/\w-])([A-Z][A-Z-]+\.md)\b", text):  # a bare design-note name: say where it is
            if m.group(1) not in ("README.md", "CHANGELOG.md"):
                missing.append(f"{f.relative_to(ROOT)}: {m.group(1)} (name it as docs/.../{m.group(1)})")
    assert not missing, missing


def test_the_project_speaks_of_the_product() -> None:
    """No work period or tracker number in the docs, the code, the benches or the tests (the word session or issue
    followed by a number): a reader has neither; history goes to CHANGELOG.md by date."""
    said = []
    files = [*_markdown(), *[p for top in TOP for p in (ROOT / top).rglob("*") if p.suffix in (".py", ".sh", ".md")]]
    for f in sorted(set(files)):
        if f.is_relative_to(ROOT / "docs" / "design"):
            continue
        for n, line in enumerate(f.read_text(encoding="utf-8").splitlines(), 1):
            if re.search(r"\b(?:[Ss]essions?|[Ii]ssues?)[ -]#?\d+\b", line):
                said.append(f"{f.relative_to(ROOT)}:{n}: {line.strip()[:100]}")
    assert not said, said


def test_the_tests_map_names_every_test_file() -> None:
    """tests/README.md (the map of the tests by package) names every test module, and only ones that exist."""
    text = (ROOT / "tests" / "README.md").read_text(encoding="utf-8")
    named = set(re.findall(r"`((?:browser/)?test_\w+\.py)`", text))
    have = {p.relative_to(ROOT / "tests").as_posix() for p in (ROOT / "tests").rglob("test_*.py")}
    assert not have - named, f"not in tests/README.md: {sorted(have - named)}"
    assert not named - have, f"named in tests/README.md but missing: {sorted(named - have)}"
