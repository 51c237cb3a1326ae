"""The README and docs/: the generated performance page matches the committed results byte for
byte, every relative link points to a file that exists, the commands they show parse, and the
README keeps the test command CI runs (`.ci/run` calls `make test`)."""

from __future__ import annotations

import re
import shlex
from pathlib import Path

import pytest

from isosr_bench import report

ROOT = Path(__file__).resolve().parents[1]
DOCS = sorted((ROOT / "docs").glob("*.md"))
PAGES = [ROOT / "README.md", *DOCS]
LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)(?:\s+\"[^\"]*\")?\)")


def test_performance_page_is_generated_from_the_results(tmp_path):
    """`python -m isosr_bench.report --docs` on the committed results gives the committed page."""
    readme = tmp_path / "README.md"
    readme.write_bytes((ROOT / "README.md").read_bytes())
    page = tmp_path / "performance.md"
    report.write_docs(report.RESULTS_DIR, page, readme, tmp_path / "priors")
    assert page.read_bytes() == (ROOT / "docs" / "performance.md").read_bytes(), \
        "docs/performance.md differs from the results: run `python -m isosr_bench.report --docs`"
    assert (tmp_path / "priors" / "cuda.json").read_bytes() == (report.PRIORS_DIR / "cuda.json").read_bytes(), \
        "the auto mode's cost table differs from the results: run `python -m isosr_bench.report --docs`"
    assert readme.read_bytes() == (ROOT / "README.md").read_bytes(), \
        "the README's figures table differs from the results: run `python -m isosr_bench.report --docs`"


def test_readme_has_the_generated_figures_table():
    text = (ROOT / "README.md").read_text()
    assert report.readme_figures(report.RESULTS_DIR) in text
    assert "docs/performance.md" in text


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.relative_to(ROOT).as_posix())
def test_relative_links_point_to_files(page):
    missing = []
    for target in LINK.findall(page.read_text()):
        if re.match(r"[a-z][a-z0-9+.-]*:", target) or target.startswith("#"):
            continue  # a URL, mailto:, or an anchor in the same page
        path = target.split("#", 1)[0]
        if not (page.parent / path).exists():
            missing.append(target)
    assert not missing, f"{page.relative_to(ROOT)} links to files that do not exist: {missing}"


def test_readme_keeps_the_ci_test_command():
    """CI (`.ci/run`) runs `make test`; the README's quick start shows it, and the Makefile has it."""
    assert re.search(r"^make test$", (ROOT / ".ci" / "run").read_text(), re.M)
    assert re.search(r"^test: ", (ROOT / "Makefile").read_text(), re.M)
    readme = (ROOT / "README.md").read_text()
    assert re.search(r"^ {4}make test\b", readme, re.M) and re.search(r"^ {4}make demo\b", readme, re.M)


def _commands(text: str) -> list[list[str]]:
    """The `isosr ...` command lines of a page's indented or fenced code, continuation lines joined
    and comments and environment assignments dropped."""
    lines, commands = text.replace("\\\n", " ").splitlines(), []
    for line in lines:
        code = line.strip()
        if not line.startswith("    "):
            continue  # indented code only
        try:
            words = shlex.split(code, comments=True)
        except ValueError:
            continue
        while words and re.match(r"^[A-Z_]+=", words[0]):
            words = words[1:]
        if (len(words) >= 2 and words[0] == "isosr" and "--help" not in words and "[" not in code
                and "..." not in " ".join(words[2:])):
            commands.append(words[1:])
    return commands


@pytest.mark.parametrize("page", [p for p in PAGES if p.name != "measurements.md"],
                         ids=lambda p: p.relative_to(ROOT).as_posix())
def test_isosr_commands_parse(page):
    """Every `isosr` command shown parses with the CLI's own parser (options and choices as --help says);
    the diary (measurements.md) keeps the commands as they were run."""
    from isosr_cli.main import build_parser

    parser = build_parser()
    commands = _commands(page.read_text())
    assert commands or page.name != "README.md"
    for words in commands:
        try:
            parser.parse_args(words)
        except SystemExit as e:
            pytest.fail(f"{page.relative_to(ROOT)}: `isosr {' '.join(words)}` does not parse (exit {e.code})")
