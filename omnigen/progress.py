"""Progress bars and summary tables, in one style for every command.

tqdm draws the bars (silent when stderr is not a terminal unless forced, so CI logs stay short);
rich draws the closing tables, as Ultralytics' commands end with a summary.
"""

from __future__ import annotations

import sys
from typing import Iterable, Sequence, TypeVar

from rich.console import Console
from rich.table import Table
from tqdm import tqdm

T = TypeVar("T")

console = Console(highlight=False, soft_wrap=True)


def progress(items: Iterable[T], desc: str, total: int | None = None, disable: bool = False, unit: str = "it") -> Iterable[T]:
    """A progress bar over `items`, shown only on a terminal, and only for work longer than a second."""
    return tqdm(items, desc=desc, total=total, unit=unit, disable=disable or not sys.stderr.isatty(),
                mininterval=0.5, delay=1.0, dynamic_ncols=True, leave=False)


def print_table(title: str, columns: Sequence[str], rows: Iterable[Sequence[object]]) -> None:
    """Print a summary table (right-aligned numbers) to stdout."""
    table = Table(title=title, title_justify="left", show_edge=False, header_style="bold")
    cells = [[_fmt(v) for v in row] for row in rows]
    # The first column names the row ('source=synthetic'): narrow consoles shrink the numbers first.
    first = max([len(columns[0])] + [len(r[0]) for r in cells if r]) if columns else 0
    for i, c in enumerate(columns):
        table.add_column(c, justify="left" if i == 0 else "right", min_width=first if i == 0 else None)
    for row in cells:
        table.add_row(*row)
    console.print(table)


def _fmt(v: object) -> str:
    if isinstance(v, float):
        return f"{v:.3f}" if abs(v) < 1000 else f"{v:,.0f}"
    if isinstance(v, int):
        return f"{v:,}"
    return str(v)
