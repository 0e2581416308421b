"""S-expressions with line numbers: :mod:`sexpdata` parses, we remember where lists start.

KiCad's board files are s-expressions. :mod:`sexpdata` reads them; a thin subclass of its
parser records the offset at which every list opens, so that an error about a footprint or
a pad can name the line of the file it comes from.
"""

from __future__ import annotations

import bisect
from typing import Any

from ..errors import InputError

__all__ = ["SexprDoc", "parse_sexpr"]


class SexprDoc:
    """A parsed s-expression document and the line of each of its lists.

    Attributes
    ----------
    root : list
        The top-level expression (``[Symbol('kicad_pcb'), ...]``); atoms are ``int``,
        ``float``, ``str`` (quoted strings) or :class:`sexpdata.Symbol` (a ``str`` too).
    source : str
        File name used in messages.
    """

    def __init__(self, root: list, starts: dict[int, int], text: str, source: str) -> None:
        self.root = root
        self.source = source
        self._starts = starts
        self._newlines = [i for i, ch in enumerate(text) if ch == "\n"]

    def line_of_offset(self, offset: int) -> int:
        """1-based line of a character offset."""
        return bisect.bisect_left(self._newlines, offset) + 1

    def line(self, node: Any) -> int | None:
        """1-based line where list ``node`` opens, or ``None`` if it is not one of ours."""
        off = self._starts.get(id(node))
        return None if off is None else self.line_of_offset(off)

    def error(self, node: Any, message: str) -> InputError:
        """``InputError("FILE:LINE: message")`` for a problem found at ``node``."""
        line = self.line(node)
        where = f"{self.source}:{line}" if line is not None else self.source
        return InputError(f"{where}: {message}")


def _parser_class():
    import sexpdata

    class _Parser(sexpdata.Parser):
        """sexpdata's parser, also recording where every list opens."""

        def __init__(self, text: str) -> None:
            # No atom means nil/true/false: KiCad writes yes/no and plain words.
            super().__init__(text, nil=None, true=None, false=None)
            self.starts: dict[int, int] = {}
            self.keep: list[list] = []
            self.last_closed = 0

        def parse_sexp(self, i):  # noqa: D401 - sexpdata's name
            end, sexp = super().parse_sexp(i)
            # Called with i just after "(" for every nested list (0 for the top level).
            self.starts[id(sexp)] = max(i - 1, 0)
            self.keep.append(sexp)
            self.last_closed = max(i - 1, 0)
            return end, sexp

    return _Parser, sexpdata


def parse_sexpr(text: str, *, source: str) -> SexprDoc:
    """Parse one s-expression document.

    Parameters
    ----------
    text : str
        The file's text.
    source : str
        File name for messages.

    Returns
    -------
    SexprDoc

    Raises
    ------
    InputError
        ``FILE:LINE: ...`` for unbalanced brackets, an unterminated string, text after
        the expression, or an empty file.
    """
    parser_cls, sexpdata = _parser_class()
    parser = parser_cls(text)
    lines = [i for i, ch in enumerate(text) if ch == "\n"]

    def at(offset: int) -> str:
        return f"{source}:{bisect.bisect_left(lines, offset) + 1}"

    try:
        end, top = parser.parse_sexp(0)
    except sexpdata.ExpectClosingBracket:
        raise InputError(f"{at(parser.last_closed)}: '(' opened here is never closed "
                         f"(file truncated or a ')' missing)") from None
    except (AttributeError, IndexError):
        # sexpdata fails this way on a string that never ends.
        raise InputError(f"{source}: a quoted string never ends (unbalanced '\"')") from None
    if end < len(text):
        raise InputError(f"{at(end)}: unexpected ')' (one ')' too many)")
    top = [t for t in top if not (isinstance(t, str) and not t.strip())]
    if not top:
        raise InputError(f"{source}:1: empty file (no s-expression)")
    if len(top) > 1 or not isinstance(top[0], list):
        raise InputError(f"{source}:1: expected one '(...)' expression; found "
                         f"{len(top)} top-level items")
    return SexprDoc(top[0], parser.starts, text, source)
