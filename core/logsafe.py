"""Client text made safe for logs and messages: a newline (or any control character) in an uploaded file's name or
an archive member's name must never start a line of its own in a log, where it could forge an entry.

``escape_control`` writes every control, line-separator and bidirectional-override character as a visible escape
(``\\x0a``, ``\\u2028``); ``EscapingFilter`` applies it to a logger's records, message and traceback alike (the
traceback's own line breaks stay, the exception messages in it are escaped); ``relabel`` writes an engine message
about the stored upload in terms of the client's file name, escaped. Upload names are also PHI-prone (DICOM exports
are often named after the patient): the API and the worker log job ids, never upload names.
"""

from __future__ import annotations

import logging
import re
import traceback

# C0 and C1 controls, DEL, line/paragraph separators, bidi embeddings, overrides and isolates
_CONTROL = re.compile("[\x00-\x1f\x7f-\x9f\u2028\u2029\u200e\u200f\u202a-\u202e\u2066-\u2069]")


def _escape_char(match: re.Match[str]) -> str:
    code = ord(match.group())
    return f"\\x{code:02x}" if code < 0x100 else f"\\u{code:04x}"


def escape_control(text: str) -> str:
    """``text`` with every control character written as a visible escape (one line, nothing hidden)."""
    return _CONTROL.sub(_escape_char, text)


_UPLOAD_NAME = re.compile(r"(^|\b(?:in|of|from) )upload\d*\b")  # the store names it upload (upload2: a second)


def relabel(message: str, filename: str | None) -> str:
    """An engine message about the stored upload (named ``upload``: at the start, or after "in", "of" or "from")
    in terms of the client's file name (escaped)."""
    name = escape_control(filename) if filename else "the upload"
    return _UPLOAD_NAME.sub(lambda m: m.group(1) + name, message)


def safe_traceback(exc: BaseException) -> str:
    """The traceback of ``exc`` (and its causes) with each exception's message escaped."""
    chain: list[BaseException] = []
    seen: set[int] = set()
    cur: BaseException | None = exc
    while cur is not None and id(cur) not in seen:
        chain.append(cur)
        seen.add(id(cur))
        cur = cur.__cause__ if cur.__cause__ is not None else (None if cur.__suppress_context__ else cur.__context__)
    parts: list[str] = []
    for k, item in enumerate(reversed(chain)):
        if k:
            parts.append("\nThe above exception led to the following one:\n\n")
        parts.append("Traceback (most recent call last):\n")
        parts.extend(traceback.format_tb(item.__traceback__))
        parts.append(escape_control(f"{type(item).__qualname__}: {item}"))
    return "".join(parts)


class EscapingFilter(logging.Filter):
    """Escapes control characters in the records of the logger it is attached to (see the module docstring)."""

    def filter(self, record: logging.LogRecord) -> bool:
        record.msg = escape_control(record.getMessage())
        record.args = None
        if record.exc_info and record.exc_info[1] is not None and not record.exc_text:
            record.exc_text = safe_traceback(record.exc_info[1])
        return True


def safe_logger(name: str) -> logging.Logger:
    """``logging.getLogger(name)`` with an :class:`EscapingFilter` (attached once)."""
    log = logging.getLogger(name)
    if not any(isinstance(f, EscapingFilter) for f in log.filters):
        log.addFilter(EscapingFilter())
    return log
