"""MkDocs hooks for gcrsky's docs (``hooks:`` in mkdocs.yml), and the updater of the architecture page.

The build checks that ``docs/architecture.md`` still describes the package:

* its "Measured" block (between ``<!-- measured:begin -->`` and ``<!-- measured:end -->``)
  must equal the current ``python -m gcrsky.checks.imports`` report;
* its layer table must name every module of every layer, and no module that is gone.

Either drift logs a WARNING, so ``mkdocs build --strict`` fails and says how to fix it.
``python docs/_hooks.py`` rewrites the Measured block from the current source (the table's
roles are prose: edit them by hand).

``gcrsky/checks/imports.py`` is loaded from its file (standard library only), so the
check does not import gcrsky, jax or anything else.
"""

from __future__ import annotations

import importlib.util
import logging
import re
import sys
from pathlib import Path

log = logging.getLogger("mkdocs.plugins.gcrsky_docs")

ROOT = Path(__file__).resolve().parents[1]
PAGE = ROOT / "docs" / "architecture.md"
BEGIN, END = "<!-- measured:begin -->", "<!-- measured:end -->"
UPDATE = "run `.venv/bin/python docs/_hooks.py` to refresh it"


def _imports_module():
    spec = importlib.util.spec_from_file_location("_gcrsky_checks_imports", ROOT / "gcrsky" / "checks" / "imports.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _measured_block(report: str) -> str:
    return f"{BEGIN}\n\n{report.strip()}\n\n{END}"


def _current_block(markdown: str) -> str | None:
    m = re.search(re.escape(BEGIN) + r".*?" + re.escape(END), markdown, flags=re.DOTALL)
    return m.group(0) if m else None


def _table_problems(markdown: str, imports) -> list[str]:
    """Modules missing from (or stale in) the layer table, as messages."""
    graph = imports.import_graph(ROOT / "gcrsky")
    pkgs = {m for m in graph if any(o.startswith(m + ".") for o in graph)}
    actual: dict[str, set[str]] = {}
    for mod in graph:
        if mod in pkgs or mod == "gcrsky":
            continue
        actual.setdefault(imports.layer_of(mod), set()).add(mod.rsplit(".", 1)[-1])
    listed: dict[str, set[str]] = {}
    for line in markdown.split(BEGIN, 1)[0].splitlines():  # the hand-written table, not the report
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) >= 3 and cells[0] in imports.LAYERS:
            listed[cells[0]] = set(re.findall(r"(?:^|<br>)`([\w]+)`:", cells[2]))
    problems = []
    for layer in imports.LAYERS:
        have, want = listed.get(layer, set()), actual.get(layer, set())
        if layer not in listed:
            problems.append(f"layer {layer!r} has no row in the layer table")
        if want - have:
            problems.append(f"layer {layer!r}: modules not in the table: {sorted(want - have)}")
        if have - want:
            problems.append(f"layer {layer!r}: modules in the table that no longer exist: {sorted(have - want)}")
    return problems


def on_page_markdown(markdown: str, page, config, files, **kwargs) -> str:
    if page.file.src_uri != "architecture.md":
        return markdown
    imports = _imports_module()
    fresh = _measured_block(imports.report(ROOT / "gcrsky"))
    current = _current_block(markdown)
    if current is None:
        log.warning("architecture.md: no %s ... %s block for the measured import report", BEGIN, END)
    elif current != fresh:
        log.warning("architecture.md: the measured import report is out of date; %s", UPDATE)
    for problem in _table_problems(markdown, imports):
        log.warning("architecture.md: %s (edit the layer table)", problem)
    return markdown


def main() -> int:
    text = PAGE.read_text()
    current = _current_block(text)
    if current is None:
        print(f"{PAGE}: no {BEGIN} ... {END} block", file=sys.stderr)
        return 1
    imports = _imports_module()
    fresh = _measured_block(imports.report(ROOT / "gcrsky"))
    if current == fresh:
        print(f"{PAGE}: measured block up to date")
    else:
        PAGE.write_text(text.replace(current, fresh))
        print(f"{PAGE}: measured block updated")
    for problem in _table_problems(text, imports):
        print(f"{PAGE}: {problem} (edit the layer table)", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
