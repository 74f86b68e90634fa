"""docs/configuration.md's table lists every `QUIETFRAME_*` name, and only names in use: every
name the code uses (Python, shell, the Makefile, the Dockerfile, pyproject.toml, deploy/, the C++
ops and their CMake file), every field of the service's Settings (read by prefix, so its names
need not be spelled out in the code) and every name another page mentions has a row; a row whose
name nothing uses any more fails too."""

from __future__ import annotations

import os
import re
from collections.abc import Iterator
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
PAGE = ROOT / "docs" / "configuration.md"
# A name, not a prefix: `QUIETFRAME_` followed by words, never ending in `_` (a prefix such as
# f"QUIETFRAME_{field}" or startswith("QUIETFRAME_") is no name).
NAME = re.compile(r"QUIETFRAME_[A-Z0-9]+(?:_[A-Z0-9]+)*")
CODE_SUFFIXES = {".py", ".sh", ".toml", ".cc", ".h"}
CODE_NAMES = {"Makefile", "Dockerfile", "CMakeLists.txt"}
SKIPPED_FOLDERS = {"build", "__pycache__", "node_modules"}  # and every hidden one (.venv*, .git)


def walk(top: Path) -> Iterator[Path]:
    for folder, subfolders, files in os.walk(top):
        subfolders[:] = [d for d in subfolders
                         if not d.startswith(".") and d not in SKIPPED_FOLDERS]
        for name in files:
            yield Path(folder) / name


def names_in(paths) -> dict[str, set[str]]:
    """name -> the files (relative to the repository) that hold it."""
    found: dict[str, set[str]] = {}
    for path in paths:
        try:
            text = path.read_text(errors="ignore")
        except OSError:
            continue
        for name in NAME.findall(text):
            found.setdefault(name, set()).add(str(path.relative_to(ROOT)))
    return found


def code_files() -> Iterator[Path]:
    for path in walk(ROOT):
        if path.suffix in CODE_SUFFIXES or path.name in CODE_NAMES or (
            path.relative_to(ROOT).parts[0] == "deploy"
        ):
            yield path


def settings_names() -> set[str]:
    from quietframe.service.settings import Settings

    prefix = Settings.model_config["env_prefix"]
    assert prefix == "QUIETFRAME_"
    return {prefix + field.upper() for field in Settings.model_fields}


def table_rows() -> dict[str, list[str]]:
    """The table's rows: name -> its cells (layer, meaning, default)."""
    lines = PAGE.read_text().splitlines()
    headers = [i for i, line in enumerate(lines) if line.startswith("| variable |")]
    assert len(headers) == 1, "docs/configuration.md holds one table of variables"
    rows: dict[str, list[str]] = {}
    for line in lines[headers[0] + 2:]:
        if not line.startswith("|"):
            break
        cells = [c.strip() for c in line.strip().strip("|").split(" | ")]
        match = re.fullmatch(r"`(QUIETFRAME_[A-Z0-9_]+)`", cells[0])
        assert match, f"one name per row, in backticks: {line}"
        assert len(cells) == 4 and all(cells), f"name, layer, meaning, default: {line}"
        assert match[1] not in rows, f"{match[1]} has two rows"
        rows[match[1]] = cells[1:]
    return rows


def test_every_name_the_code_uses_is_in_the_table():
    rows = table_rows()
    missing = {name: sorted(files) for name, files in names_in(code_files()).items()
               if name not in rows}
    assert not missing, f"add these to docs/configuration.md: {missing}"


def test_every_service_setting_is_in_the_table():
    rows = table_rows()
    missing = sorted(settings_names() - rows.keys())
    assert not missing, f"Settings fields without a row in docs/configuration.md: {missing}"
    for name in settings_names():
        assert rows[name][0].startswith("service"), (name, rows[name][0])


def test_the_table_lists_no_name_out_of_use():
    used = set(names_in(code_files())) | settings_names()
    gone = sorted(set(table_rows()) - used)
    assert not gone, f"docs/configuration.md lists names nothing uses: {gone}"


def test_the_other_pages_mention_only_names_in_the_table():
    rows = table_rows()
    pages = [p for p in walk(ROOT / "docs") if p.suffix == ".md" and p != PAGE]
    pages += [ROOT / "README.md", ROOT / "NOTICE.md", ROOT / "experiments" / "README.md"]
    unknown = {name: sorted(files) for name, files in names_in(pages).items()
               if name not in rows}
    assert not unknown, f"pages mention names docs/configuration.md does not list: {unknown}"


def test_the_pages_that_list_settings_point_to_the_table():
    for page in ("docs/README.md", "docs/service.md", "docs/deployment.md"):
        assert "configuration.md" in (ROOT / page).read_text(), page
