"""The one error type of dataset loading, and the helpers that keep its message on one line."""

from __future__ import annotations

REPR_MAX = 60  # characters of a value's repr quoted in a message


def one_line(text: str) -> str:
    """``text`` with every line break and other non-printable character escaped
    (``\\n``, ``\\x00``, ``\\u2028``): a message is always exactly one line, whatever
    a file name or a file's bytes contain."""
    if text.isprintable():
        return text
    return "".join(c if c.isprintable() else c.encode("unicode_escape").decode("ascii") for c in text)


def short_repr(value: object, limit: int = REPR_MAX) -> str:
    """``repr(value)`` on one line, cut to ``limit`` characters (ending in ``...``)."""
    if type(value).__module__ == "numpy" and hasattr(value, "item"):  # np.float64(9.0) -> 9.0
        try:
            value = value.item()
        except Exception:
            pass
    try:
        r = repr(value)
    except Exception:  # a hostile object's __repr__
        r = f"<{type(value).__name__}>"
    r = one_line(r)
    return r if len(r) <= limit else r[: limit - 3] + "..."


class DatasetError(ValueError):
    """A dataset does not meet the contract; the message (one line) says where and why."""

    def __init__(self, message: str):
        super().__init__(one_line(str(message)))
