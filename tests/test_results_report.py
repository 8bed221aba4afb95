"""benchmarks/results/README.md: its status table is what benchmarks/report.py generates from the
committed JSON, every section that code or the README points to by title exists, and every result
file it names is in the repository."""

import pathlib
import re

from benchmarks import report

ROOT = pathlib.Path(__file__).resolve().parents[1]
RESULTS_README = ROOT / "benchmarks" / "results" / "README.md"


def test_status_table_is_generated_from_the_committed_json():
    assert report.main(["--check"]) == 0, "run python -m benchmarks.report"
    for paths in report.CURRENT.values():
        for path in paths:
            assert (report.RESULTS / path).exists(), path


def _pointer_sources():
    files = [ROOT / "README.md"]
    for folder in ("engine", "morphopt", "benchmarks", "tests", "studies", "designs"):
        files += [p for p in (ROOT / folder).rglob("*") if p.suffix in (".py", ".toml", ".md")
                  and "results" not in p.parts]
    return files


def _titles(text: str) -> list[str]:
    """The quoted section titles after each mention of benchmarks/results/README.md (comment marks
    and line breaks inside a quote read as spaces)."""
    flat = " ".join(re.sub(r"\n\s*#+\s?", " ", text).split())
    titles = []
    for match in re.finditer(r'benchmarks/results/README\.md[`),:;]*\s*((?:"[^"]+"(?:,\s*|\s+and\s+)?)+)', flat):
        titles += re.findall(r'"([^"]+)"', match.group(1))
    return titles


def test_every_pointer_to_the_results_readme_names_a_section_that_exists():
    headings = [" ".join(line.lstrip("#").split()) for line in RESULTS_README.read_text().splitlines()
                if line.startswith("#")]
    pointers = []
    for path in _pointer_sources():
        for title in _titles(path.read_text(errors="ignore")):
            title = title.rstrip(" .,").removesuffix("...").rstrip(" ,")  # "A title, ..." names its start
            pointers.append(title)
            assert any(title in heading for heading in headings), f"{path.relative_to(ROOT)}: no section {title!r}"
    assert len(pointers) >= 5  # the pattern still finds the pointers


def test_every_result_file_the_readme_names_exists():
    text = RESULTS_README.read_text()
    names = set(re.findall(r"\b((?:h100|h200|cpu)/[\w.\-]+\.(?:jsonl|json|csv\.gz|csv|png)\b)", text))
    stems = set(re.findall(r"\b((?:h100|h200|cpu)/[\w\-]+)\.\*", text))
    missing = [n for n in names if not (RESULTS_README.parent / n).exists()]
    missing += [s for s in stems if not list(RESULTS_README.parent.glob(s + ".*"))]
    assert not missing, missing
