"""The one error type the engine raises for bad input, and why a file cannot be read.

The command line turns a `FemError` into a single `error: ...` line on stderr
and exit code 2; anything else is a bug and keeps its traceback.
"""


import os
import stat


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


def not_a_file(path):
    """Why `path` is not a regular file that can be read, in a few words ("no such file", "a
    folder, not a file", "a symbolic link that loops", "a character device, not a file"), or None
    when it is one."""
    try:
        mode = os.stat(path).st_mode
    except FileNotFoundError:
        if os.path.islink(path):
            return f"a symbolic link to {excerpt(os.readlink(path))}, which does not exist"
        return "no such file"
    except OSError as error:      # ELOOP, a name too long, a folder on the way that is a file
        reason = "a symbolic link that loops" if os.path.islink(path) and error.errno == 40 else error.strerror
        return reason.lower() if reason else "cannot be read"
    if stat.S_ISREG(mode):
        return None
    kinds = {stat.S_ISDIR: "a folder", stat.S_ISCHR: "a character device", stat.S_ISBLK: "a block device",
             stat.S_ISFIFO: "a named pipe", stat.S_ISSOCK: "a socket"}
    kind = next((name for test, name in kinds.items() if test(mode)), "something")
    return f"{kind}, not a file"


def require_file(path, what="file"):
    """Raise FemError "PATH: no such WHAT" or "PATH: a folder, not a file" unless `path` is a
    regular file (what: "scene file", "mesh file", ...)."""
    reason = not_a_file(path)
    if reason == "no such file":
        raise FemError(f"{path}: no such {what}")
    if reason is not None:
        raise FemError(f"{path}: cannot read it as a {what}: {reason}")


def one_line(message):
    """A message as one line: newlines and other control characters in it (a file named with a
    newline) written as escapes, so that an `error:` line stays one line."""
    text = str(message)
    if text.isprintable():
        return text
    return "".join(c if c.isprintable() else c.encode("unicode_escape").decode("ascii") for c in text)
