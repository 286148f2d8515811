"""Sections of a docs page that a measuring script renders from its JSON, between two HTML comments."""

from __future__ import annotations

import re
from pathlib import Path


def replace_section(page: Path, begin: str, end: str, text: str) -> str:
    """``page``'s text with the section from ``begin`` to ``end`` replaced by ``text`` (which carries both)."""
    content = page.read_text()
    pattern = re.compile(re.escape(begin) + ".*?" + re.escape(end), re.DOTALL)
    if not pattern.search(content):
        raise SystemExit(f"{page}: no section between {begin} and {end}")
    return pattern.sub(lambda _: text, content)
