"""Text from templates shown in the viewer's Markdown: view and file names, reasons, meta values are data.

viser renders Markdown with raw HTML enabled (a `<script>` inside an `<iframe srcdoc>` runs), so every such
text goes through `md_text`: control characters are written out (`\\x1b`, `\\n`) and every ASCII punctuation
character is backslash-escaped, which CommonMark defines as the literal character (no tag, no emphasis, no
table cell break, no entity).
"""
from __future__ import annotations

import string
import unicodedata

_BIDI = set("\u061c\u200e\u200f\u202a\u202b\u202c\u202d\u202e\u2066\u2067\u2068\u2069\u2028\u2029")
_PUNCTUATION = set(string.punctuation)


def _visible(c: str) -> str:
    if c in _BIDI or unicodedata.category(c) == "Cc":
        return {"\n": "\\n", "\r": "\\r", "\t": "\\t"}.get(c, f"\\x{ord(c):02x}" if ord(c) < 0x100 else
                                                          f"\\u{ord(c):04x}")
    return c


def md_text(text: object) -> str:
    """`text` as Markdown that shows exactly its characters (control characters written out)."""
    shown = "".join(_visible(c) for c in str(text))
    return "".join("\\" + c if c in _PUNCTUATION else c for c in shown)
