"""The one error type the engine raises for bad input.

The command line turns a `FemError` into a single `error: ...` line on stderr
and exit code 2; anything else is a bug and keeps its traceback.
"""


class FemError(Exception):
    """Bad input: a file, a scene key or a parameter the engine cannot use.

    The message names the file (and line, where there is one) and says what is
    wrong, e.g. ``scenes/x.toml: body[0].material.E must be > 0, got -1``.
    """


def excerpt(text, limit=60):
    """A short, printable quotation of user text for a message: control characters escaped,
    at most `limit` characters (a line of a system file, a 10 kB --set value)."""
    text = str(text)
    shown = text[:limit].encode("unicode_escape").decode("ascii")
    return repr(shown + ("..." if len(text) > limit else ""))


class SizeLimitError(FemError):
    """A size over its limit (fem/limits.py), such as more tets than the memory holds: probably
    a typo in a resolution, which would exhaust the memory. The command line adds how to lift
    the limit (--allow-large)."""
