"""Progress bars and summary tables, in one style for every command.

tqdm draws the bars (silent when stderr is not a terminal unless forced, so CI logs stay short);
rich draws the closing tables, as Ultralytics' commands end with a summary.
"""

from __future__ import annotations

import sys
from typing import Iterable, Sequence, TypeVar

from rich.console import Console
from rich.table import Table
from rich.text import Text
from tqdm import tqdm

T = TypeVar("T")

console = Console(highlight=False, soft_wrap=True)


def progress(items: Iterable[T], desc: str, total: int | None = None, disable: bool = False, unit: str = "it") -> Iterable[T]:
    """A progress bar over `items`, shown only on a terminal, and only for work longer than a second."""
    return tqdm(items, desc=desc, total=total, unit=unit, disable=disable or not sys.stderr.isatty(),
                mininterval=0.5, delay=1.0, dynamic_ncols=True, leave=False)


def print_table(title: str, columns: Sequence[str], rows: Iterable[Sequence[object]]) -> None:
    """Print a summary table (right-aligned numbers) to stdout, never cutting a cell.

    A table wider than the console (80 columns in a log or a pipe) would have rich shrink its
    columns to "0.…" under headers "im… ob…": a number that cannot be read. Such a table is printed
    vertically instead, one block of `column  value` lines per row (`vertical_table`).
    """
    cells = [[_fmt(v) for v in row] for row in rows]
    if _width(columns, cells) > console.width:
        console.print(vertical_table(title, columns, cells))
        return
    table = Table(title=title, title_justify="left", show_edge=False, header_style="bold")
    for i, c in enumerate(columns):
        table.add_column(Text(c), justify="left" if i == 0 else "right", no_wrap=True)
    for row in cells:
        table.add_row(*map(Text, row))  # Text: a "[" in a frame id or path is not rich markup
    console.print(table)


def _width(columns: Sequence[str], cells: list[list[str]]) -> int:
    """The characters a table needs on one line: each column as wide as its widest cell or header,
    three between columns (rich's padding and rule)."""
    widths = [max([len(c)] + [len(r[i]) for r in cells if i < len(r)]) for i, c in enumerate(columns)]
    return sum(widths) + 3 * max(len(widths) - 1, 0) + 2


def vertical_table(title: str, columns: Sequence[str], cells: list[list[str]]) -> Table:
    """The same cells as `column  value` lines, a block per row headed by its first cell: what
    fits any width, whatever the number of columns."""
    table = Table(title=title, title_justify="left", show_edge=False, show_header=False, box=None)
    table.add_column("column", justify="left", no_wrap=True)
    table.add_column("value", justify="right", no_wrap=True)
    for k, row in enumerate(cells):
        if len(cells) > 1:
            if k:
                table.add_row("", "")
            table.add_row(Text(columns[0], style="bold"), Text(row[0], style="bold"))
            pairs = zip(columns[1:], row[1:])
        else:
            pairs = zip(columns, row)
        for name, value in pairs:
            table.add_row(Text(name), Text(value))
    return table


def _fmt(v: object) -> str:
    if isinstance(v, float):
        return f"{v:.3f}" if abs(v) < 1000 else f"{v:,.0f}"
    if isinstance(v, int):
        return f"{v:,}"
    return str(v)
