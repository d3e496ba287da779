"""Every table the command lines print (reach-driver, tools/, policy's commands) goes out here,
one way: a number is never cut to fit.

- On a terminal wide enough for it: the rich table, as built.
- On a terminal too narrow: plain aligned text in blocks of columns that each fit its width,
  the first column (the row's name) repeated in each block.
- Off a terminal (piped, redirected, a CI log): plain aligned text, one line per row at its
  natural width, so `| tail`, grep and awk see every cell whole.

Titles and captions are prose: wrapped at the console's width, never cut either.

Callers build a `rich.table.Table` as they always have and hand it to `show_table` (or, for a
`Live` view, `fitted`)."""

from __future__ import annotations

import textwrap

from rich.cells import cell_len
from rich.console import Console, RenderableType
from rich.errors import MarkupError
from rich.table import Table
from rich.text import Text

#: Between two columns of plain text.
GAP = "  "
#: Wider than any table: measuring with it gives a table's natural width.
_UNBOUNDED = 1_000_000


def natural_width(console: Console, table: Table) -> int:
    """Columns the table takes drawn without wrapping or cutting a cell."""
    options = console.options.update_width(_UNBOUNDED)
    return console.measure(table, options=options).maximum


def fits(console: Console, table: Table) -> bool:
    return natural_width(console, table) <= console.width


def plain_text(value: object, joiner: str = "; ") -> str:
    """A cell, header, title or caption as plain text on one line (markup read, lines of a
    multi-line cell joined by `joiner`)."""
    if value is None:
        return ""
    if isinstance(value, Text):
        text = value.plain
    elif isinstance(value, str):
        try:
            text = Text.from_markup(value).plain
        except MarkupError:
            text = value
    else:
        text = str(value)
    return joiner.join(part.strip() for part in text.splitlines() if part.strip())


def _aligned(text: str, width: int, justify: str) -> str:
    pad = width - cell_len(text)
    if justify == "right":
        return " " * pad + text
    if justify == "center":
        return " " * (pad // 2) + text + " " * (pad - pad // 2)
    return text + " " * pad


def _blocks(widths: list[int], width: int | None) -> list[list[int]]:
    """Column indices per block: all in one without a width, else the first column and as
    many of the others as fit `width` (at least one each)."""
    if width is None or len(widths) <= 1:
        return [list(range(len(widths)))]
    blocks: list[list[int]] = []
    block = [0]
    used = widths[0]
    for i in range(1, len(widths)):
        if len(block) > 1 and used + len(GAP) + widths[i] > width:
            blocks.append(block)
            block, used = [0], widths[0]
        block.append(i)
        used += len(GAP) + widths[i]
    blocks.append(block)
    return blocks


def _prose(text: str, width: int | None) -> list[str]:
    if not text:
        return []
    return textwrap.wrap(text, width, break_on_hyphens=False) if width else [text]


def plain_lines(
    table: Table, width: int | None = None, prose_width: int | None = None
) -> list[str]:
    """The table as plain aligned text: its title, then per block of columns a header line
    and a line per row (a rule of dashes where the table has a section break), then its
    caption. Every cell whole: `width` only splits the columns into blocks; the title and
    caption, prose, are wrapped at `prose_width`."""
    columns = table.columns
    headers = [plain_text(c.header, " ") for c in columns]
    cells = [[plain_text(cell) for cell in c.cells] for c in columns]
    n_rows = max((len(c) for c in cells), default=0)
    for column in cells:
        column += [""] * (n_rows - len(column))
    widths = [
        max([cell_len(h), *(cell_len(v) for v in col)])
        for h, col in zip(headers, cells, strict=True)
    ]
    justify = [str(c.justify) for c in columns]
    lines: list[str] = []
    lines += _prose(plain_text(table.title, " "), prose_width)
    for n, block in enumerate(_blocks(widths, width)):
        if n:
            lines.append("")
        span = sum(widths[i] for i in block) + len(GAP) * (len(block) - 1)
        lines.append(GAP.join(_aligned(headers[i], widths[i], justify[i]) for i in block).rstrip())
        for r in range(n_rows):
            row = GAP.join(_aligned(cells[i][r], widths[i], justify[i]) for i in block)
            lines.append(row.rstrip())
            if r < len(table.rows) and table.rows[r].end_section and r < n_rows - 1:
                lines.append("-" * span)
    lines += _prose(plain_text(table.caption, " "), prose_width)
    return lines


def fitted(console: Console, table: Table) -> RenderableType:
    """What to show for `table` on `console`: the table if it fits (and the console is a
    terminal), else its plain text (in blocks fitting a terminal's width)."""
    if console.is_terminal and fits(console, table):
        return table
    width = console.width if console.is_terminal else None
    text = "\n".join(plain_lines(table, width, console.width))
    return Text(text, no_wrap=True, overflow="ignore")


def show_table(console: Console, table: Table) -> None:
    """Print `table` on `console` by the rules of this module."""
    if console.is_terminal and fits(console, table):
        console.print(table)
        return
    width = console.width if console.is_terminal else None
    for line in plain_lines(table, width, console.width):
        console.print(line, markup=False, highlight=False, emoji=False, soft_wrap=True)
