"""The report as a list of blocks (headings, paragraphs, tables, figures), written as one
self-contained HTML page (figures embedded as PNG) or as a PDF by matplotlib's PDF backend (text
and tables flowed onto A4 pages, each figure on a page of its own)."""

from __future__ import annotations

import base64
import html
import io
import math
import textwrap
from dataclasses import dataclass, field
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
from matplotlib.backends.backend_pdf import PdfPages
from matplotlib.figure import Figure


@dataclass(frozen=True)
class Heading:
    text: str
    anchor: str = ""


@dataclass(frozen=True)
class Paragraph:
    text: str
    emphasis: bool = False  # a statement the reader must not miss


@dataclass(frozen=True)
class Cell:
    """A table cell: what it shows, and the number behind it (HTML keeps it in data-value, and
    `name` in data-name, so that a program can read the report's numbers back exactly)."""

    text: str
    value: float | None = None
    name: str = ""


@dataclass(frozen=True)
class Table:
    columns: list[str]
    rows: list[list[Cell]]
    caption: str = ""
    anchor: str = ""


@dataclass(frozen=True)
class FigureBlock:
    figure: Figure
    caption: str
    anchor: str = ""


@dataclass
class Document:
    title: str
    blocks: list = field(default_factory=list)

    def add(self, *blocks) -> None:
        self.blocks.extend(blocks)


_STYLE = """
body { font-family: "DejaVu Sans", Helvetica, Arial, sans-serif; max-width: 60em; margin: 2em auto; color: #222;
       line-height: 1.4; }
h1 { font-size: 1.6em; } h2 { font-size: 1.2em; border-bottom: 1px solid #ccc; margin-top: 2em; }
table { border-collapse: collapse; margin: 0.8em 0; font-size: 0.9em; }
th, td { border: 1px solid #ccc; padding: 0.2em 0.6em; text-align: left; }
td.number { text-align: right; font-variant-numeric: tabular-nums; }
p.caption { font-size: 0.85em; color: #555; margin: -0.5em 0 1em 0; max-width: 50em; }
figure { margin: 1em 0; } figure img { max-width: 100%; } figcaption { font-size: 0.85em; color: #555; }
p.emphasis { border-left: 4px solid #c60; background: #fff4e8; padding: 0.4em 0.8em; }
"""


def write_html(document: Document, path: Path) -> None:
    parts = [
        '<!doctype html>\n<html lang="en">\n<head>\n<meta charset="utf-8">\n'
        f"<title>{html.escape(document.title)}</title>\n<style>{_STYLE}</style>\n</head>\n<body>\n<h1>{html.escape(document.title)}</h1>\n"
    ]
    for block in document.blocks:
        anchor = f' id="{html.escape(block.anchor)}"' if getattr(block, "anchor", "") else ""
        if isinstance(block, Heading):
            parts.append(f"<h2{anchor}>{html.escape(block.text)}</h2>\n")
        elif isinstance(block, Paragraph):
            emphasis = ' class="emphasis"' if block.emphasis else ""
            parts.append(f"<p{emphasis}>{html.escape(block.text)}</p>\n")
        elif isinstance(block, Table):
            parts.append(_html_table(block, anchor))
        elif isinstance(block, FigureBlock):
            buffer = io.BytesIO()
            block.figure.savefig(buffer, format="png", dpi=110)
            encoded = base64.b64encode(buffer.getvalue()).decode("ascii")
            parts.append(
                f'<figure{anchor}><img alt="{html.escape(block.caption)}" src="data:image/png;base64,{encoded}">'
                f"<figcaption>{html.escape(block.caption)}</figcaption></figure>\n"
            )
    parts.append("</body>\n</html>\n")
    path.write_text("".join(parts), encoding="utf-8")


def _html_table(table: Table, anchor: str) -> str:
    head = (
        "<thead><tr>" + "".join(f"<th>{html.escape(column)}</th>" for column in table.columns) + "</tr></thead>"
        if any(table.columns)
        else ""
    )
    rows = []
    for row in table.rows:
        cells = []
        for cell in row:
            if cell.value is None:  # a number's cell stays right-aligned when it has none ("—")
                cells.append(('<td class="number">' if cell.name else "<td>") + f"{html.escape(cell.text)}</td>")
            else:
                cells.append(
                    f'<td class="number" data-name="{html.escape(cell.name)}" data-value="{float(cell.value)!r}">'
                    f"{html.escape(cell.text)}</td>"
                )
        rows.append("<tr>" + "".join(cells) + "</tr>")
    # The caption below the table as a paragraph: a <caption> would wrap to the table's width.
    caption = f'<p class="caption">{html.escape(table.caption)}</p>\n' if table.caption else ""
    return f"<table{anchor}>{head}<tbody>{''.join(rows)}</tbody></table>\n{caption}"


# A4 portrait, inches, and the layout of its pages.
_PAGE_IN = (8.27, 11.69)
_MARGIN_IN = 0.6
_LINE_IN = 0.16
_TEXT_POINTS = 8.5
_WRAP_CHARS = 100
_TABLE_CHARS = 112  # monospace characters a line of a table holds
_FIGURE_DPI = 200
_STYLES = {
    "title": {"fontsize": 14, "fontweight": "bold"},
    "heading": {"fontsize": 11, "fontweight": "bold"},
    "emphasis": {"fontsize": _TEXT_POINTS, "color": "#a04000", "fontweight": "bold"},
    "mono": {"fontsize": _TEXT_POINTS - 1, "family": "monospace"},
    "caption": {"fontsize": _TEXT_POINTS - 0.5, "color": "#444444"},
    "text": {"fontsize": _TEXT_POINTS},
}


def write_pdf(document: Document, path: Path) -> None:
    """The blocks flowed onto A4 pages top to bottom: text and tables as lines, figures (drawn at
    200 dpi) at the column's width with their captions, each kept whole on one page."""
    with PdfPages(path, metadata={"Title": document.title, "Creator": "Fractoscope"}) as pdf:
        pages = _Pages(pdf)
        for text in textwrap.wrap(document.title, 58):
            pages.line("title", text)
        pages.line("text", "")
        for index, block in enumerate(document.blocks):
            following = document.blocks[index + 1] if index + 1 < len(document.blocks) else None
            if isinstance(block, Heading):
                pages.line("text", "")
                # A heading stays with what follows: a whole figure, or a few lines.
                keep = pages.figure_height_in(following) / _LINE_IN if isinstance(following, FigureBlock) else 4
                pages.line("heading", block.text, keep_with_next=keep)
            elif isinstance(block, Paragraph):
                for text in textwrap.wrap(block.text, _WRAP_CHARS):
                    pages.line("emphasis" if block.emphasis else "text", text)
            elif isinstance(block, Table):
                for text in _text_table(block):
                    pages.line("mono", text)
            elif isinstance(block, FigureBlock):
                pages.figure(block)
        pages.close()


class _Pages:
    """The page being filled and the height used on it, inches from its top edge."""

    def __init__(self, pdf: PdfPages):
        self._pdf = pdf
        self._page = None
        self._used_in = 0.0

    def line(self, kind: str, text: str, *, keep_with_next: float = 0) -> None:
        height_in = _LINE_IN * (1.6 if kind == "title" else 1.25 if kind == "heading" else 1.0)
        self._room(height_in + _LINE_IN * keep_with_next)
        if text:  # plain text: lines hold users' names (image files), never mathtext
            self._page.text(
                _MARGIN_IN / _PAGE_IN[0],
                1 - self._used_in / _PAGE_IN[1],
                text,
                va="top",
                ha="left",
                parse_math=False,
                **_STYLES[kind],
            )
        self._used_in += height_in

    def figure_height_in(self, block: FigureBlock) -> float:
        """The height a figure and its caption take on the page."""
        width_in, height_in = block.figure.get_size_inches()
        scale = min(1.0, (_PAGE_IN[0] - 2 * _MARGIN_IN) / width_in)
        return height_in * scale + _LINE_IN * (len(textwrap.wrap(block.caption, _WRAP_CHARS + 10)) + 1)

    def figure(self, block: FigureBlock) -> None:
        buffer = io.BytesIO()
        block.figure.savefig(buffer, format="png", dpi=_FIGURE_DPI)
        buffer.seek(0)
        pixels = plt.imread(buffer)
        width_in = min(_PAGE_IN[0] - 2 * _MARGIN_IN, pixels.shape[1] / _FIGURE_DPI)
        height_in = width_in * pixels.shape[0] / pixels.shape[1]
        caption = textwrap.wrap(block.caption, _WRAP_CHARS + 10)
        self._room(self.figure_height_in(block))
        left, top = _MARGIN_IN / _PAGE_IN[0], 1 - self._used_in / _PAGE_IN[1]
        axes = self._page.add_axes(
            (left, top - height_in / _PAGE_IN[1], width_in / _PAGE_IN[0], height_in / _PAGE_IN[1])
        )
        axes.imshow(pixels, interpolation="antialiased")
        axes.set_axis_off()
        self._used_in += height_in + 0.05
        for text in caption:
            self.line("caption", text)
        self._used_in += _LINE_IN / 2

    def close(self) -> None:
        if self._page is not None:
            self._pdf.savefig(self._page)
            plt.close(self._page)
            self._page = None

    def _room(self, height_in: float) -> None:
        """A new page unless `height_in` more fits on this one (or this one is still empty)."""
        if (
            self._page is not None
            and self._used_in + height_in > _PAGE_IN[1] - _MARGIN_IN
            and self._used_in > _MARGIN_IN
        ):
            self.close()
        if self._page is None:
            self._page = plt.figure(figsize=_PAGE_IN)
            self._used_in = _MARGIN_IN


def _text_table(table: Table) -> list[str]:
    """A table as aligned monospace lines (its caption wrapped below); a last column too wide for
    the page wraps onto lines of its own."""
    rows = [table.columns] + [[cell.text for cell in row] for row in table.rows]
    widths = [max(len(row[i]) for row in rows) for i in range(len(table.columns))]
    widths[-1] = max(8, min(widths[-1], _TABLE_CHARS - sum(widths[:-1]) - 2 * (len(widths) - 1)))
    numeric = [any(row[i].value is not None for row in table.rows) for i in range(len(table.columns))]

    def lines(values) -> list[str]:
        *first, last = values
        wrapped = textwrap.wrap(last, widths[-1]) or [""]
        head = [
            value.rjust(width) if is_number else value.ljust(width)
            for value, width, is_number in zip(first, widths, numeric)
        ]
        indent = [" " * width for width in widths[:-1]]
        tail = wrapped[0].rjust(widths[-1]) if numeric[-1] else wrapped[0]
        return ["  ".join(head + [tail])] + ["  ".join(indent + [more]) for more in wrapped[1:]]

    out = lines(rows[0]) + ["  ".join("-" * width for width in widths)] if any(table.columns) else []
    for row in rows[1:]:
        out += lines(row)
    if table.caption:
        out += textwrap.wrap(table.caption, _WRAP_CHARS)
    return out + [""]


def number(value: float | None, digits: int = 4) -> str:
    """A value for a table: `digits` significant digits, "—" when unknown."""
    if value is None or not math.isfinite(value):
        return "—"
    return f"{value:.{digits}g}"
