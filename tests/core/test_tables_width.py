"""Summary tables read at 80 columns and in logs: no cell is cut (issue 45: `omnigen eval`'s tables
printed "0.…" under headers "im… ob… AP…" below about 100 columns)."""

from __future__ import annotations

import re

from omnigen import progress

COLUMNS = ["split", "images", "objects", "AP50", "AP50:95", "precision", "recall", "corner error px",
           "adherence deg", "corner error rel"]
ROWS = [["test", 12, 104, 0.1234, 0.0567, 0.5, 0.4, 12.3, 4.94, 0.143],
        ["test/aerial", 4, 30, 0.1, 0.05, 0.5, 0.4, 12.3, 4.94, 0.143]]


def _printed(monkeypatch, capsys, width: int, columns=COLUMNS, rows=ROWS) -> str:
    monkeypatch.setattr(progress.console, "width", width)
    progress.print_table("eval", columns, rows)
    return capsys.readouterr().out


def test_a_wide_table_at_80_columns_cuts_no_cell(monkeypatch, capsys):
    out = _printed(monkeypatch, capsys, 80)
    assert "…" not in out
    assert max(len(line) for line in out.splitlines()) <= 80
    for name in COLUMNS:
        assert name in out
    for value in ("0.123", "0.057", "12.300", "4.940", "test/aerial", "104"):
        assert value in out


def test_a_table_that_fits_stays_a_table(monkeypatch, capsys):
    out = _printed(monkeypatch, capsys, 80, ["split", "frames"], [["test", 3], ["train", 14]])
    assert re.search(r"split\s+┃\s+frames", out) and "train │" in out


def test_cells_are_not_markup(monkeypatch, capsys):
    out = _printed(monkeypatch, capsys, 80, ["id [b]", "n"], [["frame[bold]1", 3]])
    assert "id [b]" in out and "frame[bold]1" in out
