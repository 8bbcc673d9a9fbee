"""The documentation a user has: inside the repository, links that resolve, and the contract's
rules table identical to the rules the code applies."""

from __future__ import annotations

import re
from pathlib import Path

from tertiary import contract as schema

ROOT = Path(__file__).resolve().parents[1]
USER_TEXTS = [ROOT / "README.md", ROOT / "datasets" / "README.md", *sorted((ROOT / "docs").glob("*.md"))]


def test_nothing_points_outside_the_repository():
    for path in USER_TEXTS:
        text = path.read_text(encoding="utf-8")
        assert "../shared" not in text and "/work/" not in text, f"{path.name} points outside the repository"


def test_every_relative_link_resolves():
    for path in USER_TEXTS:
        for target in re.findall(r"\]\(([^)#]+)(?:#[^)]*)?\)", path.read_text(encoding="utf-8")):
            if "://" in target:
                continue
            assert (path.parent / target).exists(), f"{path.name}: broken link {target}"


def test_contract_rules_in_the_docs_are_the_code_rules():
    assert schema.rules_markdown().strip() in (ROOT / "docs" / "data-contract.md").read_text(encoding="utf-8")


def test_shipped_scenarios_do_not_need_files_outside_the_install():
    for toml in (ROOT / "datasets").glob("*.toml"):
        text = toml.read_text(encoding="utf-8")
        m = re.search(r'truth_file\s*=\s*"([^"]*)"', text)
        if m and m.group(1):
            assert (ROOT / "datasets" / m.group(1)).is_file(), f"{toml.name}: {m.group(1)} is not shipped"


def test_tests_use_no_file_outside_the_repository():
    """A test reading a file beside the clone skips on a fresh clone (and CI fails on the skip)."""
    outside = ("parents[2]", '"shared"')
    for path in set((ROOT / "tests").glob("*.py")) - {Path(__file__).resolve()}:
        text = path.read_text(encoding="utf-8")
        assert not any(o in text for o in outside), f"{path.name} reads outside the repository"


def test_the_readme_is_a_manual_not_a_history():
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    assert len(text.splitlines()) <= 150
    assert not re.search(r"\b20\d\d-\d\d-\d\d\b", text), "a date in the README: history lives in git"


def test_code_and_docs_carry_no_history():
    """No issue numbers, "was …" figures or documents outside the repository in docstrings and
    docs, and no dates in the code (a recording's date in the docs is data, not history)."""
    history = re.compile(r"\b[Ii]ssues? \d+|\(was [0-9]|seeds?/|digest ``")
    dated = re.compile(r"\b20\d\d-\d\d-\d\d\b")
    code = [*ROOT.joinpath("tertiary").rglob("*.py"), *ROOT.joinpath("safety").rglob("*.py")]
    bad = [f"{p.relative_to(ROOT)}:{i}" for p in [*USER_TEXTS, *code]
           for i, line in enumerate(p.read_text(encoding="utf-8").splitlines(), 1)
           if history.search(line) or (p.suffix == ".py" and dated.search(line))]
    assert not bad, bad
