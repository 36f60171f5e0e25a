"""A static evaluation report: tables, figures and text into ``index.html``, ``tables/*.csv``, ``results.json``.

The report takes numbers, not recordings. :class:`Report` collects items in order (sections
start headings), :meth:`Report.write` renders them into a folder that opens offline (inline
CSS, images as relative links), and :func:`check_report` re-reads such a folder and lists
what is wrong with it. Table cells are numbers, strings, ``None`` (missing) or
:class:`MeanStd`; HTML shows them rounded, CSV and JSON keep every digit.
"""

from __future__ import annotations

import csv
import dataclasses
import html
import io
import json
import math
import os
import re
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from datetime import UTC, datetime
from html.parser import HTMLParser
from pathlib import Path
from typing import TYPE_CHECKING, Any
from urllib.parse import unquote

import numpy as np

if TYPE_CHECKING:
    from matplotlib.figure import Figure
    from rich.console import Console

INDEX = "index.html"
RESULTS = "results.json"
FIGURE_SUFFIXES = (".png", ".svg", ".jpg", ".jpeg", ".gif")
MISSING = "\u2013"  # en dash
_KEY = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]*$")


# -- values -------------------------------------------------------------------------------------


@dataclass(frozen=True)
class MeanStd:
    """A mean and standard deviation in the column's unit; ``n`` samples when known."""

    mean: float
    std: float
    n: int | None = None

    @classmethod
    def of(cls, values: Iterable[float] | np.ndarray) -> MeanStd:
        """Mean and population standard deviation of the finite ``values`` (NaN when there are none)."""
        a = np.asarray(values, dtype=float).ravel()
        a = a[np.isfinite(a)]
        if a.size == 0:
            return cls(math.nan, math.nan, 0)
        return cls(float(a.mean()), float(a.std()), int(a.size))

    def __str__(self) -> str:
        return format_cell(self)


Cell = float | int | str | bool | MeanStd | None


@dataclass(frozen=True)
class Column:
    """A table column: display ``name``, ``unit`` ("" when dimensionless) and its stable ``key`` (units in the key)."""

    name: str
    unit: str
    key: str

    @property
    def header(self) -> str:
        return f"{self.name} ({self.unit})" if self.unit else self.name


@dataclass(frozen=True)
class Table:
    """A table as added: cells as given (None where missing) and the HTML's decimals per column."""

    key: str
    title: str
    columns: tuple[Column, ...]
    rows: tuple[tuple[Cell, ...], ...]
    caption: str = ""
    decimals: tuple[int | None, ...] = ()

    def formatted(self) -> list[list[str]]:
        """The rows as display strings, rounded per column."""
        decimals = self.decimals or (None,) * len(self.columns)
        return [[format_cell(c, d) for c, d in zip(row, decimals)] for row in self.rows]

    def numeric(self, column: int) -> bool:
        """Whether every present cell of ``column`` is a number (shown right-aligned)."""
        present = [row[column] for row in self.rows if row[column] is not None]
        return bool(present) and all(_is_number(c) or isinstance(c, MeanStd) for c in present)


@dataclass(frozen=True)
class FigureItem:
    """An image's bytes and its file name suffix; written to :attr:`path` inside the report folder."""

    key: str
    title: str
    data: bytes
    suffix: str
    caption: str = ""

    @property
    def path(self) -> str:
        return f"figures/{self.key}{self.suffix}"


@dataclass(frozen=True)
class Text:
    """Plain text or the Markdown subset of :func:`render_markdown`."""

    key: str
    text: str


@dataclass(frozen=True)
class Section:
    """A heading and the items under it; the report's first section has no title."""

    key: str
    title: str
    items: list[Table | FigureItem | Text] = field(default_factory=list)


# -- number formatting --------------------------------------------------------------------------


def _is_number(c: object) -> bool:
    return isinstance(c, int | float) and not isinstance(c, bool)


def _magnitude_decimals(magnitude: float, significant: int) -> int:
    """Decimals that show ``magnitude`` with ``significant`` digits, within 0..6."""
    if not math.isfinite(magnitude) or magnitude == 0:
        return 2
    return min(6, max(0, significant - 1 - math.floor(math.log10(abs(magnitude)))))


def column_decimals(cells: Sequence[Cell]) -> int | None:
    """Decimals for a column: 2 significant digits of its median std, or else 3 of its median magnitude.

    None when the column has no float to round (integers and strings are shown as they are).
    """
    stds = [c.std for c in cells if isinstance(c, MeanStd) and math.isfinite(c.std) and c.std > 0]
    if stds:
        return _magnitude_decimals(float(np.median(stds)), 2)
    values = [c.mean if isinstance(c, MeanStd) else c for c in cells]
    floats = [abs(c) for c in values if isinstance(c, float) and math.isfinite(c) and c != 0]
    if floats:
        return _magnitude_decimals(float(np.median(floats)), 3)
    return None


def format_cell(cell: Cell, decimals: int | None = None) -> str:
    """A cell as display text: ``MISSING`` for None, ``"0.14 ± 0.05"`` for a :class:`MeanStd`."""
    if cell is None:
        return MISSING
    if isinstance(cell, bool):
        return "yes" if cell else "no"
    if isinstance(cell, str):
        return cell
    if isinstance(cell, MeanStd) and not math.isfinite(cell.std):
        return format_cell(cell.mean, decimals)
    if isinstance(cell, MeanStd):
        d = decimals if decimals is not None else _magnitude_decimals(cell.std or cell.mean, 2)
        return f"{_format_float(cell.mean, d)} ± {_format_float(cell.std, d)}"
    if isinstance(cell, int):
        return str(cell)
    d = decimals if decimals is not None else _magnitude_decimals(cell, 3)
    return _format_float(cell, d)


def _format_float(x: float, decimals: int) -> str:
    if math.isnan(x):
        return MISSING
    if math.isinf(x):
        return "inf" if x > 0 else "-inf"
    if x != 0 and (abs(x) >= 1e6 or abs(x) < 10.0**-decimals / 2):
        return f"{x:.3g}"
    return f"{x:.{decimals}f}"


# -- JSON -----------------------------------------------------------------------------------------


def to_jsonable(obj: Any) -> Any:
    """``obj`` as plain JSON data: numpy arrays and scalars to lists and numbers, non-finite floats to None."""
    if isinstance(obj, MeanStd):
        return {"mean": to_jsonable(obj.mean), "std": to_jsonable(obj.std), "n": obj.n}
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return to_jsonable(dataclasses.asdict(obj))
    if isinstance(obj, np.ndarray):
        return to_jsonable(obj.tolist())
    if isinstance(obj, np.generic):
        return to_jsonable(obj.item())
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if obj is None or isinstance(obj, str | int | bool):
        return obj
    if isinstance(obj, os.PathLike):
        return os.fspath(obj)
    if isinstance(obj, Mapping):
        return {str(k): to_jsonable(v) for k, v in obj.items()}
    if isinstance(obj, Iterable):
        return [to_jsonable(v) for v in obj]
    raise TypeError(f"cannot write {type(obj).__name__} to JSON")


# -- the builder ----------------------------------------------------------------------------------


def slug(text: str) -> str:
    """A lower-case key from ``text``: runs of other characters become ``_``; ``%`` becomes ``pct``."""
    return re.sub(r"[^a-z0-9]+", "_", text.replace("%", "pct").lower()).strip("_")


def _cell(value: Any) -> Cell:
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and math.isnan(value):
        return None
    if isinstance(value, MeanStd) and not math.isfinite(value.mean):
        return None
    if value is None or isinstance(value, str | int | float | bool | MeanStd):
        return value
    raise TypeError(f"a table cell is a number, a string, None or MeanStd, not {type(value).__name__}")


class Report:
    """An evaluation report built item by item; :meth:`write` renders it.

    A key is unique among the items of its kind (sections, tables, figures, texts, JSON items;
    a table and a figure may share one) and names the item's file (``tables/KEY.csv``,
    ``figures/KEY.png``) and its anchor in the page (``#table-KEY``, ``#section-KEY``, ...).
    """

    def __init__(self, title: str, meta: Mapping[str, Any] | None = None) -> None:
        self.title = title
        self.meta: dict[str, Any] = dict(meta or {})
        self.sections: list[Section] = [Section("top", "")]
        self.data: dict[str, Any] = {}
        self._keys: dict[str, set[str]] = {kind: set() for kind in ("section", "table", "figure", "text", "data")}
        self._keys["section"].add("top")
        self.written_to: Path | None = None

    def _claim(self, kind: str, key: str) -> str:
        if not _KEY.match(key):
            raise ValueError(f"key {key!r}: letters, digits, '_', '.' and '-' only, not starting with a dot or dash")
        if key in self._keys[kind]:
            raise ValueError(f"{kind} key {key!r} is already used in this report")
        self._keys[kind].add(key)
        return key

    def section(self, title: str, key: str | None = None) -> Report:
        """Start a section (its key defaults to the title's :func:`slug`): items added after it go under this heading."""
        self.sections.append(Section(self._claim("section", key or slug(title)), title))
        return self

    def add_text(self, key: str, text: str) -> Report:
        """A paragraph of plain text or a small Markdown subset (blank-line paragraphs, ``-`` lists,
        ``**bold**``, ``*italic*``, `` `code` ``, ``[text](link)``)."""
        self.sections[-1].items.append(Text(self._claim("text", key), text))
        return self

    def add_table(
        self,
        key: str,
        title: str,
        columns: Sequence[str],
        rows: Iterable[Sequence[Any] | Mapping[str, Any]],
        caption: str = "",
        units: Mapping[str, str] | None = None,
        decimals: int | Mapping[str, int] | None = None,
    ) -> Report:
        """A table; ``units`` maps a column name to its unit (shown in the header, part of the column's key).

        A row is a sequence in column order or a mapping by column name (absent names are missing).
        Cells are numbers, strings, None or NaN (missing) or :class:`MeanStd`. ``decimals``
        overrides the automatic rounding of the HTML, for all columns or by column name.
        """
        units = dict(units or {})
        unknown = set(units) - set(columns)
        if isinstance(decimals, Mapping):
            unknown |= set(decimals) - set(columns)
        if unknown:
            raise ValueError(f"table {key!r}: no column named {sorted(unknown)}")
        cols = tuple(Column(c, units.get(c, ""), slug(f"{c} {units.get(c, '')}")) for c in columns)
        col_keys = [c.key for c in cols]
        if len(set(col_keys)) != len(col_keys) or "" in col_keys:
            raise ValueError(f"table {key!r}: column keys {col_keys} are empty or not unique")
        table_rows = []
        for row in rows:
            if isinstance(row, Mapping) and set(row) - set(columns):
                raise ValueError(f"table {key!r}: a row has cells for no column: {sorted(set(row) - set(columns))}")
            cells = [row.get(c) for c in columns] if isinstance(row, Mapping) else list(row)
            if len(cells) != len(cols):
                raise ValueError(f"table {key!r}: a row has {len(cells)} cells for {len(cols)} columns")
            table_rows.append(tuple(_cell(c) for c in cells))
        by_column = list(zip(*table_rows)) if table_rows else [() for _ in cols]
        if isinstance(decimals, Mapping):
            digits = tuple(decimals.get(c.name, column_decimals(cells)) for c, cells in zip(cols, by_column))
        else:
            digits = tuple(decimals if decimals is not None else column_decimals(cells) for cells in by_column)
        table = Table(self._claim("table", key), title, cols, tuple(table_rows), caption, digits)
        self.sections[-1].items.append(table)
        return self

    def add_figure(
        self, key: str, title: str, figure: str | os.PathLike[str] | Figure, caption: str = "", dpi: int = 110
    ) -> Report:
        """A figure from an image file (PNG, SVG, JPEG, GIF) or a matplotlib Figure (rendered to PNG now)."""
        if isinstance(figure, str | os.PathLike):
            source = Path(figure)
            suffix = source.suffix.lower()
            if suffix not in FIGURE_SUFFIXES:
                raise ValueError(f"figure {key!r}: {source.name} is not one of {', '.join(FIGURE_SUFFIXES)}")
            data = source.read_bytes()
        else:
            buffer = io.BytesIO()
            figure.savefig(buffer, format="png", dpi=dpi)
            data, suffix = buffer.getvalue(), ".png"
        self.sections[-1].items.append(FigureItem(self._claim("figure", key), title, data, suffix, caption))
        return self

    def add_json(self, key: str, obj: Any) -> Report:
        """Raw numbers for ``results.json`` under ``data.KEY`` (name units in the keys: ``error_mm``)."""
        self.data[self._claim("data", key)] = to_jsonable(obj)
        return self

    @property
    def tables(self) -> list[Table]:
        return [i for s in self.sections for i in s.items if isinstance(i, Table)]

    @property
    def figures(self) -> list[FigureItem]:
        return [i for s in self.sections for i in s.items if isinstance(i, FigureItem)]

    def results(self) -> dict[str, Any]:
        """Everything as plain JSON data (the content of ``results.json``)."""
        return {
            "title": self.title,
            "meta": to_jsonable(self.meta),
            "sections": [
                {"key": s.key, "title": s.title, "items": [{"kind": _kind(i), "key": i.key} for i in s.items]}
                for s in self.sections
            ],
            "tables": {t.key: _table_json(t) for t in self.tables},
            "figures": {f.key: {"title": f.title, "caption": f.caption, "path": f.path} for f in self.figures},
            "text": {i.key: i.text for s in self.sections for i in s.items if isinstance(i, Text)},
            "data": self.data,
        }

    def write(self, out_dir: str | os.PathLike[str]) -> Path:
        """Write the report into ``out_dir``; returns the path of ``index.html``.

        Every file goes through a temporary name and a rename, and ``index.html`` is removed
        first and written last: after a crash the folder has no page, never a partial one.
        Files of an earlier report in the folder that this one does not write are removed.
        """
        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
        index = out / INDEX
        index.unlink(missing_ok=True)
        previous = _previous_files(out)
        files: list[str] = []
        for f in self.figures:
            _write_atomic(out / f.path, f.data)
            files.append(f.path)
        for t in self.tables:
            _write_atomic(out / "tables" / f"{t.key}.csv", table_csv(t).encode())
            files.append(f"tables/{t.key}.csv")
        results = self.results()
        results["meta"].setdefault("generated_utc", datetime.now(UTC).isoformat(timespec="seconds"))
        results["files"] = files
        _write_atomic(out / RESULTS, (json.dumps(results, indent=1, allow_nan=False, ensure_ascii=False) + "\n").encode())
        for stale in previous - set(files):
            (out / stale).unlink(missing_ok=True)
        _write_atomic(index, render_html(self, results["meta"]).encode())
        self.written_to = index
        return index


def _write_atomic(path: Path, data: bytes) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    tmp.write_bytes(data)
    tmp.replace(path)


def _previous_files(out: Path) -> set[str]:
    """The figure and table files an earlier report listed in its results.json."""
    try:
        listed = json.loads((out / RESULTS).read_text(encoding="utf-8")).get("files", [])
    except (OSError, ValueError, AttributeError):
        return set()
    return {f for f in listed if isinstance(f, str) and re.fullmatch(r"(figures|tables)/[^/\\]+", f)}


# -- CSV and JSON of a table ----------------------------------------------------------------------


def _mean_std_columns(table: Table) -> list[bool]:
    return [any(isinstance(row[i], MeanStd) for row in table.rows) for i in range(len(table.columns))]


def table_csv(table: Table) -> str:
    """The table as CSV with every digit: header of column keys, a mean/std column pair for
    :class:`MeanStd` columns (``KEY_mean``, ``KEY_std``), empty cells where missing."""
    split = _mean_std_columns(table)
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    header: list[str] = []
    for col, pair in zip(table.columns, split):
        header += [f"{col.key}_mean", f"{col.key}_std"] if pair else [col.key]
    writer.writerow(header)
    for row in table.rows:
        out: list[str] = []
        for cell, pair in zip(row, split):
            if pair:
                mean, std = (cell.mean, cell.std) if isinstance(cell, MeanStd) else (cell, None)
                out += [_csv_value(mean), _csv_value(std)]
            else:
                out.append(_csv_value(cell))
        writer.writerow(out)
    return buffer.getvalue()


def _csv_value(cell: Cell) -> str:
    if cell is None:
        return ""
    if isinstance(cell, float):
        return repr(cell)
    return str(cell)


def _table_json(table: Table) -> dict[str, Any]:
    return {
        "title": table.title,
        "caption": table.caption,
        "csv": f"tables/{table.key}.csv",
        "columns": [{"key": c.key, "name": c.name, "unit": c.unit} for c in table.columns],
        "rows": [{c.key: to_jsonable(cell) for c, cell in zip(table.columns, row)} for row in table.rows],
    }


# -- HTML -----------------------------------------------------------------------------------------

_CSS = """
:root { --ink: #1d2430; --muted: #5b6675; --line: #d9dee5; --band: #f5f7fa; --accent: #2b6cb0; }
* { box-sizing: border-box; }
body { margin: 0; color: var(--ink); background: #fff;
  font: 15px/1.5 system-ui, -apple-system, "Segoe UI", Roboto, "Helvetica Neue", Arial, sans-serif; }
main { max-width: 1080px; margin: 0 auto; padding: 2rem 1.5rem 4rem; }
h1 { font-size: 1.7rem; margin: 0 0 .3rem; }
h2 { font-size: 1.3rem; margin: 2.5rem 0 .8rem; padding-bottom: .3rem; border-bottom: 2px solid var(--line); }
h3 { font-size: 1.05rem; margin: 1.8rem 0 .5rem; }
a { color: var(--accent); }
code { font: .9em ui-monospace, "SFMono-Regular", Menlo, Consolas, monospace; background: var(--band); padding: 0 .25em; }
dl.meta { display: grid; grid-template-columns: max-content 1fr; gap: .1rem 1rem; color: var(--muted); margin: .5rem 0 1.5rem; }
dl.meta dt { font-weight: 600; } dl.meta dd { margin: 0; }
nav.toc { background: var(--band); border: 1px solid var(--line); border-radius: 6px; padding: .8rem 1.2rem; }
nav.toc ol { margin: .2rem 0; padding-left: 1.3rem; } nav.toc li { margin: .1rem 0; }
nav.toc > strong { display: block; margin-bottom: .2rem; }
.table-wrap { overflow-x: auto; }
table { border-collapse: collapse; margin: .4rem 0; font-variant-numeric: tabular-nums; }
th, td { padding: .3rem .75rem; border-bottom: 1px solid var(--line); text-align: left; white-space: nowrap; }
thead th { border-bottom: 2px solid var(--ink); font-weight: 600; }
tbody tr:nth-child(even) { background: var(--band); }
.num { text-align: right; }
td.missing { color: var(--muted); text-align: center; }
p.caption, figcaption { color: var(--muted); font-size: .9rem; margin: .3rem 0 0; max-width: 80ch; }
p.files { font-size: .85rem; margin: .2rem 0 0; }
figure { margin: 1rem 0; }
figure img { max-width: 100%; height: auto; border: 1px solid var(--line); }
footer { margin-top: 3rem; color: var(--muted); font-size: .85rem; border-top: 1px solid var(--line); padding-top: .8rem; }
"""


def _e(text: object) -> str:
    return html.escape(str(text), quote=True)


def _kind(item: Section | Table | FigureItem | Text) -> str:
    return {Section: "section", Table: "table", FigureItem: "figure", Text: "text"}[type(item)]


def anchor(item: Section | Table | FigureItem | Text) -> str:
    """The element id of an item in the page: its kind and key, ``table-force_errors``."""
    return _e(f"{_kind(item)}-{item.key}")


def _safe_href(href: str) -> bool:
    scheme = re.match(r"^([a-zA-Z][a-zA-Z0-9+.-]*):", href)
    return scheme is None or scheme.group(1).lower() in ("http", "https", "mailto")


def _inline(text: str) -> str:
    """Escaped inline Markdown: code spans first (kept verbatim), then links, bold and italic."""
    out = []
    for i, part in enumerate(re.split(r"`([^`]*)`", text)):
        if i % 2:
            out.append(f"<code>{_e(part)}</code>")
            continue
        s = _e(part)

        def link(m: re.Match[str]) -> str:
            href = html.unescape(m.group(2))
            return f'<a href="{_e(href)}">{m.group(1)}</a>' if _safe_href(href) else m.group(0)

        s = re.sub(r"\[([^\]]+)\]\(([^)\s]+)\)", link, s)
        s = re.sub(r"\*\*(.+?)\*\*", r"<strong>\1</strong>", s)
        s = re.sub(r"(?<![\w*])\*(?!\s)(.+?)(?<!\s)\*(?![\w*])", r"<em>\1</em>", s)
        out.append(s)
    return "".join(out)


def render_markdown(text: str) -> str:
    """A small Markdown subset as HTML: paragraphs, ``-``/``*`` lists and :func:`_inline` spans."""
    blocks = []
    for block in re.split(r"\n\s*\n", text.strip()):
        lines = [line.strip() for line in block.splitlines() if line.strip()]
        if not lines:
            continue
        if all(re.match(r"^[-*] ", line) for line in lines):
            items = "".join(f"<li>{_inline(line[2:])}</li>" for line in lines)
            blocks.append(f"<ul>{items}</ul>")
        else:
            blocks.append(f"<p>{_inline(' '.join(lines))}</p>")
    return "\n".join(blocks)


def _table_html(t: Table) -> str:
    numeric = [t.numeric(i) for i in range(len(t.columns))]
    head = "".join(
        f'<th scope="col" class="num">{_e(c.header)}</th>' if num else f'<th scope="col">{_e(c.header)}</th>'
        for c, num in zip(t.columns, numeric)
    )
    body = []
    for raw, shown in zip(t.rows, t.formatted()):
        cells = []
        for cell, text, num in zip(raw, shown, numeric):
            if cell is None:
                cells.append(f'<td class="missing" title="missing">{MISSING}</td>')
            else:
                cells.append(f'<td class="num">{_e(text)}</td>' if num else f"<td>{_e(text)}</td>")
        body.append(f"<tr>{''.join(cells)}</tr>")
    caption = f'<p class="caption">{_inline(t.caption)}</p>' if t.caption else ""
    return (
        f'<section class="table" id="{anchor(t)}"><h3>{_e(t.title)}</h3>'
        f'<div class="table-wrap"><table><thead><tr>{head}</tr></thead><tbody>{"".join(body)}</tbody></table></div>'
        f'{caption}<p class="files"><a href="tables/{_e(t.key)}.csv">CSV</a></p></section>'
    )


def _figure_html(f: FigureItem) -> str:
    caption = f"<figcaption>{_inline(f.caption)}</figcaption>" if f.caption else ""
    return (
        f'<section class="figure" id="{anchor(f)}"><h3>{_e(f.title)}</h3>'
        f'<figure><a href="{_e(f.path)}"><img src="{_e(f.path)}" alt="{_e(f.title)}" loading="lazy"></a>{caption}</figure>'
        "</section>"
    )


def _toc_html(report: Report) -> str:
    entries = []
    for s in report.sections:
        named = [i for i in s.items if isinstance(i, Table | FigureItem)]
        if s.title:
            sub = "".join(f'<li><a href="#{anchor(i)}">{_e(i.title)}</a></li>' for i in named)
            entries.append(f'<li><a href="#{anchor(s)}">{_e(s.title)}</a>' + (f"<ol>{sub}</ol>" if sub else "") + "</li>")
        else:
            entries += [f'<li><a href="#{anchor(i)}">{_e(i.title)}</a></li>' for i in named]
    return f'<nav class="toc"><strong>Contents</strong><ol>{"".join(entries)}</ol></nav>' if entries else ""


def render_html(report: Report, meta: Mapping[str, Any] | None = None) -> str:
    """The whole page as one string (static, no scripts, no external resources)."""
    meta = report.meta if meta is None else meta
    parts = [
        "<!DOCTYPE html>",
        '<html lang="en"><head><meta charset="utf-8">',
        '<meta name="viewport" content="width=device-width, initial-scale=1">',
        f"<title>{_e(report.title)}</title><style>{_CSS}</style></head>",
        f"<body><main><header><h1>{_e(report.title)}</h1>",
    ]
    if meta:
        rows = "".join(f"<dt>{_e(k)}</dt><dd>{_e(v)}</dd>" for k, v in meta.items())
        parts.append(f'<dl class="meta">{rows}</dl>')
    parts.append(_toc_html(report) + "</header>")
    for s in report.sections:
        if s.title:
            parts.append(f'<section class="section" id="{anchor(s)}"><h2>{_e(s.title)}</h2>')
        for item in s.items:
            if isinstance(item, Table):
                parts.append(_table_html(item))
            elif isinstance(item, FigureItem):
                parts.append(_figure_html(item))
            else:
                parts.append(f'<div class="text" id="{anchor(item)}">{render_markdown(item.text)}</div>')
        if s.title:
            parts.append("</section>")
    parts.append(
        f'<footer>Every number of this page, unrounded: <a href="{RESULTS}">{RESULTS}</a>; '
        "each table as CSV beside it in <code>tables/</code>.</footer></main></body></html>"
    )
    return "\n".join(parts) + "\n"


# -- checking a written report --------------------------------------------------------------------

_VOID = frozenset({"area", "base", "br", "col", "embed", "hr", "img", "input", "link", "meta", "source", "track", "wbr"})


class _PageChecker(HTMLParser):
    """Collects structure problems (every non-void element closed, in order), ids and local links."""

    def __init__(self) -> None:
        super().__init__(convert_charrefs=True)
        self.open: list[tuple[str, int]] = []
        self.problems: list[str] = []
        self.ids: list[str] = []
        self.links: list[tuple[str, str, int]] = []
        self.doctype = False

    def handle_decl(self, decl: str) -> None:
        self.doctype = self.doctype or decl.lower().startswith("doctype html")

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        line = self.getpos()[0]
        values = dict(attrs)
        if values.get("id"):
            self.ids.append(str(values["id"]))
        for attr in ("src", "href"):
            if values.get(attr) is not None:
                self.links.append((tag, str(values[attr]), line))
        if tag == "img" and not values.get("alt"):
            self.problems.append(f"index.html line {line}: <img> without alt text")
        if tag not in _VOID:
            self.open.append((tag, line))

    def handle_startendtag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        if tag not in _VOID:
            self.problems.append(f"index.html line {self.getpos()[0]}: <{tag}/> is not a void element")
        self.handle_starttag(tag, attrs)
        if tag not in _VOID:
            self.open.pop()

    def handle_endtag(self, tag: str) -> None:
        line = self.getpos()[0]
        if tag in _VOID:
            self.problems.append(f"index.html line {line}: end tag </{tag}> of a void element")
        elif not any(t == tag for t, _ in self.open):
            self.problems.append(f"index.html line {line}: </{tag}> closes nothing")
        else:
            while self.open:
                t, opened = self.open.pop()
                if t == tag:
                    break
                self.problems.append(f"index.html line {line}: </{tag}> closes <{tag}> before <{t}> (line {opened})")

    def finish(self) -> list[str]:
        self.close()
        problems = list(self.problems)
        problems += [f"index.html line {line}: <{tag}> is never closed" for tag, line in self.open]
        if not self.doctype:
            problems.append("index.html: no <!DOCTYPE html>")
        return problems


def _is_local(link: str) -> bool:
    return not re.match(r"^([a-zA-Z][a-zA-Z0-9+.-]*:|//|#)", link) and link != ""


def check_report(out_dir: str | os.PathLike[str]) -> list[str]:
    """Problems of a written report, as messages (empty when it is sound).

    Checks that ``index.html`` parses with every element closed in order (stricter than HTML5,
    which lets some end tags out: the writer never does), that every local ``src``/``href`` and
    ``#anchor`` resolves, that ``results.json`` loads, and that every table has its CSV with as
    many rows as the JSON and every figure its image.
    """
    out = Path(out_dir)
    index = out / INDEX
    if not index.is_file():
        return [f"{index}: missing (never written, or the writer stopped before the end)"]
    problems: list[str] = []
    checker = _PageChecker()
    try:
        checker.feed(index.read_text(encoding="utf-8"))
        problems += checker.finish()
    except UnicodeDecodeError as exc:
        return [f"index.html: not UTF-8 ({exc})"]
    duplicates = sorted({i for i in checker.ids if checker.ids.count(i) > 1})
    problems += [f"index.html: id {i!r} is used more than once" for i in duplicates]
    for tag, link, line in checker.links:
        if link.startswith("#") and link[1:] not in checker.ids:
            problems.append(f"index.html line {line}: <{tag}> links to #{link[1:]}, which is not on the page")
        elif _is_local(link) and link.startswith("/"):
            problems.append(f"index.html line {line}: <{tag}> links to the absolute path {link}; the folder would not move")
        elif _is_local(link):
            target = out / unquote(link.split("#")[0].split("?")[0])
            if not target.is_file():
                problems.append(f"index.html line {line}: <{tag}> links to {link}, which does not exist")
            elif target.stat().st_size == 0:
                problems.append(f"index.html line {line}: <{tag}> links to {link}, which is empty")
    problems += _check_results(out)
    return problems


def _check_results(out: Path) -> list[str]:
    try:
        results = json.loads((out / RESULTS).read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        return [f"{RESULTS}: cannot be read ({exc})"]
    problems = []
    for key, table in results.get("tables", {}).items():
        path = out / "tables" / f"{key}.csv"
        if not path.is_file():
            problems.append(f"table {key}: {path.relative_to(out)} is missing")
            continue
        with path.open(newline="", encoding="utf-8") as f:
            n_rows = sum(1 for _ in csv.reader(f)) - 1
        if n_rows != len(table.get("rows", [])):
            problems.append(f"table {key}: CSV has {n_rows} rows, {RESULTS} has {len(table.get('rows', []))}")
    for key, figure in results.get("figures", {}).items():
        if not (out / figure.get("path", "")).is_file():
            problems.append(f"figure {key}: {figure.get('path')} is missing")
    return problems


# -- terminal -------------------------------------------------------------------------------------


def print_summary(report: Report, console: Console | None = None) -> None:
    """The report's tables in the terminal with rich, rounded as in the page, then where it was written."""
    from rich.console import Console
    from rich.markup import escape
    from rich.table import Table as RichTable

    console = console or Console()
    console.print(f"[bold]{escape(report.title)}[/bold]")
    for t in report.tables:
        rich_table = RichTable(
            title=escape(t.title), caption=escape(t.caption) or None, title_justify="left", caption_justify="left"
        )
        for i, c in enumerate(t.columns):
            rich_table.add_column(escape(c.header), justify="right" if t.numeric(i) else "left")
        for raw, shown in zip(t.rows, t.formatted()):
            rich_table.add_row(*(f"[dim]{s}[/dim]" if r is None else escape(s) for r, s in zip(raw, shown)))
        console.print(rich_table)
    if report.figures:
        console.print(f"{len(report.figures)} figures: " + ", ".join(escape(f.title) for f in report.figures))
    if report.written_to is not None:
        console.print(f"report: {report.written_to}")
