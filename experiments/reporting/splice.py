"""A generated block in a Markdown file: the text between a begin and an end marker, rewritten whole."""

from __future__ import annotations


def check_markers(text: str, begin: str, end: str, name: str) -> None:
    """A ValueError unless ``text`` (the file ``name``) holds one ``begin`` ... ``end`` block."""
    if text.count(begin) != 1 or text.count(end) != 1 or text.index(begin) > text.index(end):
        raise ValueError(f"{name} must hold one {begin} ... {end} block")


def replace_block(text: str, block: str, begin: str, end: str) -> str:
    """``text`` with what lies between ``begin`` and ``end`` replaced by ``block``."""
    check_markers(text, begin, end, "the text")
    head, rest = text.split(begin)
    _, tail = rest.split(end)
    return f"{head}{begin}\n{block}\n{end}{tail}"
