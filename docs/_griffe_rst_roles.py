"""Griffe extension for the docs build: read gcrsky's docstrings as written, without editing them.

gcrsky's docstrings are Google style with Sphinx/RST habits in the prose.  Before
mkdocstrings parses them this extension rewrites, in memory only:

1. RST roles (``:func:`x```, ``:class:`~a.B```, ``:mod:``, ``:data:``, ...) into
   *optional* autorefs cross-references: a link when the target is rendered somewhere
   in the site, plain code otherwise (no warning either way).  Bare and relative names
   are resolved in the docstring's scope, as Sphinx would; ``~`` shows the last part only.
2. RST "simple tables" (``=====  =====`` borders) into Markdown tables.
3. Sphinx-style ``#:`` comments above a module or class attribute (``LAYERS``,
   ``DEFAULT_TOL``, ...) into that attribute's docstring, so it is rendered.
4. Continuation lines of a section item (``Raises:``, ``Args:``, ...) written at the
   item's own indentation: they are indented one more level, so that griffe reads them
   as part of the item instead of a malformed new item (which warns and fails
   ``mkdocs build --strict``).  Each such fix is logged at INFO level with file:line,
   so the docstring can be fixed at the source.

Loaded from mkdocs.yml (``plugins.mkdocstrings.handlers.python.options.extensions``);
``exclude_docs`` keeps this file out of the site.
"""

from __future__ import annotations

import html
import logging
import re
from typing import Any

import griffe

_log = logging.getLogger("mkdocs.plugins.gcrsky_docs")

_ROLE_RE = re.compile(r":(?:py:)?(?P<role>func|class|mod|data|attr|meth|obj|exc|const|type):`(?P<target>[^`]+)`")
_BORDER_RE = re.compile(r"^(?P<indent>\s*)=+(?:\s+=+)+\s*$")
_SECTION_RE = re.compile(
    r"^(?P<indent>\s*)(?P<title>Args|Arguments|Params|Parameters|Keyword Args|Keyword Arguments|"
    r"Other Parameters|Raises|Exceptions|Warns|Warnings|Attributes):\s*$"
)
# The start of an item: ``name:``, ``name (type):``, ``a, b:``, ``*args:``, ``ValueError:``.
_ITEM_RE = re.compile(r"^\s*\*{0,2}[\w.]+(?:\s*,\s*\*{0,2}[\w.]+)*(?:\s*\([^)]*\))?\s*:(?:\s|$)")


class RSTRoles(griffe.Extension):
    """Rewrite RST roles, RST simple tables and mis-indented item continuations in docstrings."""

    def on_package(self, *, pkg: griffe.Module, loader: griffe.GriffeLoader, **kwargs: Any) -> None:
        template = pkg.docstring
        for obj in _walk(pkg):
            if obj.is_attribute and obj.docstring is None and template is not None:
                _comment_docstring(obj, template)
            doc = obj.docstring
            if doc is None or not doc.value:
                continue
            value = _fix_continuations(doc.value, obj, doc.lineno)
            value = _rst_tables(value)
            value = _ROLE_RE.sub(lambda m: _autoref(m, obj, loader), value)
            doc.value = value


def _walk(obj: griffe.Object):
    yield obj
    for member in obj.members.values():
        if member.is_alias:
            continue
        yield from _walk(member)


def _comment_docstring(attr: griffe.Attribute, template: griffe.Docstring) -> None:
    """Sphinx's ``#: text`` comment lines just above ``attr`` (or after it on its line) -> its docstring."""
    try:
        source = attr.module.lines
    except Exception:  # noqa: BLE001 - no source, nothing to harvest
        return
    if not attr.lineno or attr.lineno > len(source):
        return
    k = attr.lineno - 1  # 0-based index of the assignment line
    comments: list[str] = []
    j = k - 1
    while j >= 0 and source[j].lstrip().startswith("#:"):
        comments.insert(0, source[j].lstrip()[2:].strip())
        j -= 1
    if not comments and "#:" in source[k]:
        comments = [source[k].split("#:", 1)[1].strip()]
    if comments:
        attr.docstring = griffe.Docstring(
            "\n".join(comments),
            lineno=j + 2,
            endlineno=k,
            parent=attr,
            parser=template.parser,
            parser_options=template.parser_options,
        )


def _lookup(loader: griffe.GriffeLoader, path: str):
    try:
        return loader.modules_collection[path]
    except (KeyError, ValueError, griffe.AliasResolutionError, griffe.CyclicAliasError):
        return None


def _canonical(found) -> str:
    if found.is_alias:
        try:
            return found.final_target.path
        except (griffe.AliasResolutionError, griffe.CyclicAliasError):
            return found.path
    return found.path


def _resolve(target: str, obj: griffe.Object, loader: griffe.GriffeLoader) -> griffe.Object | None:
    """The object ``target`` names as seen from ``obj``'s docstring, or None."""
    if target.startswith("."):  # relative to the docstring's module
        module = obj if obj.is_module else obj.module
        target = module.path + target
    first, _, rest = target.partition(".")
    candidates = [target]
    try:
        head = obj.resolve(first)
    except (griffe.NameResolutionError, griffe.AliasResolutionError, griffe.CyclicAliasError, KeyError):
        head = None
    if head:
        candidates.insert(0, head + ("." + rest if rest else ""))
    module = obj if obj.is_module else obj.module
    candidates.append(f"{module.path}.{target}")
    if module.modules:  # a package docstring naming what its (lazily imported) submodules define
        candidates += [f"{sub.path}.{target}" for sub in module.modules.values()]
    if obj.parent is not None and obj.parent.is_class:
        candidates.append(f"{obj.parent.path}.{target}")  # a method's sibling
    for cand in candidates:
        found = _lookup(loader, cand)
        if found is not None:
            return found
    return None


def _autoref(match: re.Match, obj: griffe.Object, loader: griffe.GriffeLoader) -> str:
    raw = match["target"].strip()
    # ``title <target>`` form
    explicit = re.fullmatch(r"(?P<title>.+?)\s*<(?P<target>[^>]+)>", raw)
    if explicit:
        title, target = explicit["title"], explicit["target"]
    else:
        target = raw.lstrip("~")
        title = target.rsplit(".", 1)[-1] if raw.startswith("~") else target
    target = target.removesuffix("()")
    found = _resolve(target, obj, loader)
    path = _canonical(found) if found is not None else target
    # A module that has no section of its own (``gcrsky.solvers.cg``) links to its
    # package's page, whose docstring lists it (the second identifier is a fallback).
    fallback = ""
    if found is not None and found.is_module and "." in path:
        fallback = f' slug="{html.escape(path.rsplit(".", 1)[0], quote=True)}"'
    return (
        f'<autoref identifier="{html.escape(path, quote=True)}"{fallback} optional>'
        f"<code>{html.escape(title)}</code></autoref>"
    )


def _rst_tables(text: str) -> str:
    """RST simple tables (two or three ``===`` border lines) -> Markdown tables."""
    lines = text.split("\n")
    out: list[str] = []
    i = 0
    while i < len(lines):
        m = _BORDER_RE.match(lines[i])
        if not m:
            out.append(lines[i])
            i += 1
            continue
        border = lines[i]
        borders = [i]
        j = i + 1
        while j < len(lines) and len(borders) < 3:
            if lines[j].rstrip() == border.rstrip():
                borders.append(j)
                # a header table has three borders; stop after two unless a body follows
                if len(borders) == 2 and not (j + 1 < len(lines) and lines[j + 1].strip()
                                              and _has_closing(lines, j + 1, border)):
                    break
            elif not lines[j].strip():
                break
            j += 1
        if len(borders) < 2:
            out.append(lines[i])
            i += 1
            continue
        spans = [(s.start(), s.end()) for s in re.finditer(r"=+", border)]

        def cells(line: str) -> list[str]:
            row = []
            for k, (a, _) in enumerate(spans):
                b = spans[k + 1][0] if k + 1 < len(spans) else len(line)
                row.append(line[a:b].strip().replace("|", "\\|"))
            return row

        indent = m["indent"]
        if len(borders) == 3:
            header = [cells(ln) for ln in lines[borders[0] + 1 : borders[1]]]
            body = lines[borders[1] + 1 : borders[2]]
            head = header[0] if header else [""] * len(spans)
        else:
            body = lines[borders[0] + 1 : borders[1]]
            head = [" "] * len(spans)
        if out and out[-1].strip():
            out.append("")
        out.append(indent + "| " + " | ".join(head) + " |")
        out.append(indent + "|" + "|".join("---" for _ in spans) + "|")
        for ln in body:
            if ln.strip():
                out.append(indent + "| " + " | ".join(cells(ln)) + " |")
        i = borders[-1] + 1
        if i < len(lines) and lines[i].strip():
            out.append("")
    return "\n".join(out)


def _has_closing(lines: list[str], start: int, border: str) -> bool:
    for k in range(start, len(lines)):
        if lines[k].rstrip() == border.rstrip():
            return True
        if not lines[k].strip():
            return False
    return False


def _fix_continuations(text: str, obj: griffe.Object, lineno: int | None) -> str:
    """Indent item continuation lines that sit at the item's own indentation."""
    lines = text.split("\n")
    i = 0
    while i < len(lines):
        sec = _SECTION_RE.match(lines[i])
        if not sec:
            i += 1
            continue
        base = len(sec["indent"])
        j = i + 1
        while j < len(lines) and not lines[j].strip():
            j += 1
        if j >= len(lines):
            break
        indent = len(lines[j]) - len(lines[j].lstrip())
        if indent <= base:
            i = j
            continue
        in_item = False
        while j < len(lines):
            line = lines[j]
            if not line.strip():
                j += 1
                continue
            cur = len(line) - len(line.lstrip())
            if cur < indent:
                break
            if cur == indent:
                if _ITEM_RE.match(line):
                    in_item = True
                elif in_item:
                    lines[j] = " " * indent + line
                    where = f"{obj.filepath}:{(lineno or 0) + j}" if lineno else str(obj.filepath)
                    _log.info(
                        "gcrsky docs: %s: continuation line of a %r item is not indented "
                        "(read as a continuation): %r", where, sec["title"], line.strip()
                    )
            j += 1
        i = j
    return "\n".join(lines)
