"""Markdown tables of the benchmark scripts' rows."""

from __future__ import annotations


def markdown_table(columns: list[str], cells: list[list[str]], header: bool = True) -> str:
    """A Markdown table: the header row and rule (if ``header``), then one line per row of cells."""
    lines = ["| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)] if header else []
    return "\n".join(lines + ["| " + " | ".join(row) + " |" for row in cells])
