"""The documentation is for users: no work-log labels in the sources, the docs or the README, and
every ``init`` value :func:`esmicp.register` accepts is documented where a user looks for it (the
docstring the API reference is generated from, the command line's ``--help`` and the reference
pages). The site itself is built with warnings as errors by ``.ci/run``
(``sphinx-build -W -b html docs docs/_build/html``)."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]

#: A label that recounts a round of work ("session 12", "Session 3:", "Issue 14, fourth pass"), not
#: something a user reads.
WORK_LOG_LABEL = re.compile(r"\bsessions?\s+\d+|\bissue\s+\d+,?\s+(?:pass\s+\d+|\w+\s+pass)\b", re.IGNORECASE)
#: A citation of the project's history: an issue by number, a red-team pass, the code before a fix or a
#: commit it was compared with. What is, is stated; the history lives in git.
WORK_LOG_CITATION = re.compile(r"\bissues?[ -]#?\d+|\bred[ -]team pass|\bbefore (?:this|the) fix\b|\bparent commit\b"
                               r"|\(commit [0-9a-f]{7,40}\b", re.IGNORECASE)

#: Where a user or a contributor reads: the package's sources, the documentation, the README, the
#: benchmark scripts that write the results pages, the tests, and the build and CI files.
CHECKED = ("src", "docs", "README.md", "benchmarks", "tests", "fuzz", "CMakeLists.txt", "pyproject.toml", ".ci")
#: Text files among them (images, CSV results and the compiled module are not read).
TEXT_SUFFIXES = {".py", ".pyi", ".md", ".rst", ".txt", ".cpp", ".h", ".toml", ".cfg"}


def _texts():
    for name in CHECKED:
        root = REPO / name
        if root.is_file():
            yield root
            continue
        if not root.exists():
            continue
        for path in sorted(root.rglob("*")):
            if (path.is_file() and (path.suffix in TEXT_SUFFIXES or path.parent.name == ".ci")
                    and "_build" not in path.parts and "corpus" not in path.parts and path.resolve() != Path(__file__).resolve()):
                yield path


def test_no_work_log_labels_in_sources_docs_or_readme():
    if not (REPO / "docs").is_dir():
        pytest.skip("not run from a source tree")
    found = []
    for path in _texts():
        for number, line in enumerate(path.read_text(encoding="utf-8", errors="replace").splitlines(), 1):
            if WORK_LOG_LABEL.search(line) or WORK_LOG_CITATION.search(line):
                found.append(f"{path.relative_to(REPO)}:{number}: {line.strip()[:100]}")
    assert not found, "work-log labels (the history lives in git):\n" + "\n".join(found)


def test_the_label_pattern_catches_what_it_should():
    assert WORK_LOG_LABEL.search("measured in Session 37's run")
    assert WORK_LOG_LABEL.search("(sessions 30 and 31)")
    assert WORK_LOG_LABEL.search('docs/speed.md, "Issue 14, fourth pass"')
    assert WORK_LOG_LABEL.search("issue 13 pass 2")
    assert not WORK_LOG_LABEL.search("a sessionless run of 3 trials")
    assert not WORK_LOG_LABEL.search("a second pass over the points (issue 13 asks for it)")
    assert WORK_LOG_CITATION.search("a second pass over the points (issue 13 asks for it)")
    assert WORK_LOG_CITATION.search("## Issue 16: a red-team pass")
    assert WORK_LOG_CITATION.search("the code before this fix (commit 41af51c), measured in the same run")
    assert WORK_LOG_CITATION.search("`before`: the same script on the parent commit")
    assert WORK_LOG_CITATION.search("(docs/reliability.md, issue-16 section)")
    assert not WORK_LOG_CITATION.search("esmicp 0.1.0 at commit 444368b; see the tissue 3 scan")


def _init_names():
    from esmicp.api import INIT_NAMES

    assert {"global", "identity"} <= set(INIT_NAMES)
    return INIT_NAMES


def _missing(text: str) -> list[str]:
    return [name for name in _init_names() if not re.search(rf"['\"`]{re.escape(name)}['\"`]", text)]


def test_every_init_value_is_in_the_docstring_the_reference_is_built_from():
    import esmicp

    assert not _missing(esmicp.register.__doc__), "init values missing from register's docstring"


def test_every_init_value_is_in_the_command_lines_help():
    done = subprocess.run([sys.executable, "-m", "esmicp", "register", "--help"], capture_output=True,
                          text=True, env={**os.environ, "COLUMNS": "200"})
    assert done.returncode == 0, done.stderr
    assert not _missing(done.stdout), "init values missing from 'esmicp register --help'"


def test_every_init_value_is_in_the_user_guide():
    guide = REPO / "docs" / "guide" / "pairs.md"
    if not guide.is_file():
        pytest.skip("not run from a source tree")
    assert not _missing(guide.read_text(encoding="utf-8")), f"init values missing from {guide.name}"


def test_the_readmes_links_lead_to_files_of_the_repository():
    """The README is read on its own (not part of the site): each relative link must lead to a
    file that exists, and each link into docs/ to a page of the site's sources."""
    readme = REPO / "README.md"
    if not readme.is_file():
        pytest.skip("not run from a source tree")
    links = re.findall(r"\]\(([^)\s]+)\)", readme.read_text(encoding="utf-8"))
    relative = [link.split("#")[0] for link in links if not re.match(r"[a-z]+:", link)]
    assert relative, "the README links to no page"
    missing = [link for link in relative if link and not (REPO / link).exists()]
    assert not missing, f"README links to missing files: {missing}"


def test_every_test_the_reliability_page_names_exists():
    """docs/reliability.md lists each promise with the tests behind it (``file.py::test_name``):
    each must be a test function of that file."""
    page = REPO / "docs" / "reliability.md"
    if not page.is_file():
        pytest.skip("not run from a source tree")
    named = set(re.findall(r"`(?:tests/)?(test_\w+\.py)::(test_\w+)`", page.read_text(encoding="utf-8")))
    assert len(named) >= 20, "the page names fewer tests than it has promises"
    missing = [f"{file}::{test}" for file, test in sorted(named)
               if not re.search(rf"^def {test}\(", (REPO / "tests" / file).read_text(encoding="utf-8"), re.MULTILINE)]
    assert not missing, f"docs/reliability.md names tests that do not exist: {missing}"


#: The results pages (written by the scripts of benchmarks/) and the picture each opens on.
RESULTS_PAGES = ("measured-global", "real-scans", "merge", "bench", "bench-paper", "bench-paper-1000", "bench-honest",
                 "baselines", "speed", "scans-partial-overlap", "scans-refinement", "scans-start-drift", "uncertainty")
#: A page's picture: small enough for a page (bytes).
MAX_PICTURE_BYTES = 150_000
IMAGE_LINE = re.compile(r"^!\[(?P<alt>[^\]]+)\]\((?P<path>images/[^)\s]+\.png)\)$")


@pytest.mark.parametrize("page", RESULTS_PAGES)
def test_every_results_page_opens_on_a_picture_of_its_results(page):
    if not (REPO / "docs").is_dir():
        pytest.skip("not run from a source tree")
    lines = (REPO / "docs" / f"{page}.md").read_text(encoding="utf-8").splitlines()
    assert lines[0].startswith("# "), f"docs/{page}.md: no title on its first line"
    content = [line for line in lines[1:] if line.strip()]
    found = IMAGE_LINE.match(content[0].strip())
    assert found, f"docs/{page}.md: the first thing after the title is not a picture: {content[0][:80]!r}"
    assert len(found["alt"].split()) >= 6, f"docs/{page}.md: the picture's alt text does not say what it shows"
    picture = REPO / "docs" / found["path"]
    assert picture.is_file(), f"docs/{page}.md: {found['path']} does not exist"
    assert picture.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n", f"{found['path']}: not a PNG"
    assert picture.stat().st_size < MAX_PICTURE_BYTES, f"{found['path']}: {picture.stat().st_size} bytes"
    caption = content[1].strip()
    assert caption and not caption.startswith(("#", "!", "|", "```")), f"docs/{page}.md: no caption under the picture"
