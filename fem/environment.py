"""The environment Taichi reads as it starts, checked before it does.

Taichi ends the process, with no Python error to catch, on settings it cannot use:
HOME unset aborts `import taichi` (SIGABRT), TI_LOG_LEVEL=garbage raises there too,
TI_CPU_MAX_NUM_THREADS=0 divides by zero (SIGFPE), 100000 starts that many threads,
and an offline cache folder it cannot write crashes the process at exit (SIGSEGV),
after the run's output. So, before taichi is imported, `prepare` gives HOME the
user's home folder when it is unset and sets aside the TI_* values Taichi cannot
use; `fem.init` then raises a FemError naming them, and starts Taichi with a cache
folder checked here (`offline_cache_folder`), or raises one saying that there is none.
"""

import os
import pwd
import re
import tempfile

LOG_LEVELS = ("trace", "debug", "info", "warn", "error", "critical", "off")
# More worker threads than this is a typo: each one is an OS thread started at ti.init.
MAX_THREADS = 1024
_problems = []


def prepare():
    """Run once, before taichi is first imported."""
    if not os.environ.get("HOME"):
        os.environ["HOME"] = home_folder()
    level = os.environ.get("TI_LOG_LEVEL")
    if level and level not in LOG_LEVELS:          # Taichi takes them in lower case only
        set_aside("TI_LOG_LEVEL", f"not a Taichi log level ({', '.join(LOG_LEVELS)})")
    threads = os.environ.get("TI_CPU_MAX_NUM_THREADS")
    # ASCII digits: Python's isdigit() also takes '²', which int() and Taichi do not.
    if threads and not (re.fullmatch(r"\s*[0-9]+\s*", threads) and 1 <= int(threads) <= MAX_THREADS):
        set_aside("TI_CPU_MAX_NUM_THREADS", f"must be a whole number of threads from 1 to {MAX_THREADS}")


def home_folder() -> str:
    """The user's home folder from the password database, else the temporary folder."""
    try:
        return pwd.getpwuid(os.getuid()).pw_dir
    except KeyError:              # a user id with no entry (some containers)
        return tempfile.gettempdir()


def set_aside(name: str, why: str):
    """Remove variable `name`, which Taichi cannot use, and remember why for problems()."""
    value = os.environ.pop(name)
    _problems.append(f"environment variable {name}={value[:40]!r}: {why}; unset it or correct it")


def problems() -> list[str]:
    """What prepare() set aside, one sentence each."""
    return list(_problems)


def offline_cache_folder() -> tuple[str | None, str]:
    """(folder, note): the folder for Taichi's offline cache, and a note for the user when it is
    not the one asked for. Asked for: TI_OFFLINE_CACHE_FILE_PATH, else Taichi's own default
    under XDG_CACHE_HOME or ~/.cache; where no file can be made there, Taichi's default, then a
    folder of this user's in the temporary folder; None, and why, if none can be written:
    Taichi would crash at exit (SIGSEGV), even told to keep no cache."""
    default = os.path.join(os.environ.get("XDG_CACHE_HOME") or os.path.join(os.environ["HOME"], ".cache"),
                           "taichi", "ticache")
    asked = os.environ.pop("TI_OFFLINE_CACHE_FILE_PATH", None) or default
    fallback = os.path.join(tempfile.gettempdir(), f"softfem-taichi-cache-{os.getuid()}")
    if writable(asked):
        return asked, ""
    unwritable = f"Taichi's kernel cache folder {asked} cannot be written"
    if default != asked and writable(default):
        return default, f"{unwritable}; using {default}"
    if writable(fallback) and os.stat(fallback).st_uid == os.getuid():     # not another user's
        return fallback, f"{unwritable}; using {fallback}"
    return None, (f"{unwritable}, nor {fallback}, and Taichi crashes without one; set "
                  "TI_OFFLINE_CACHE_FILE_PATH to a folder you can write")


def writable(folder: str) -> bool:
    """True when folder exists or can be made, and a file can be created in it."""
    try:
        os.makedirs(folder, exist_ok=True)
        descriptor, probe = tempfile.mkstemp(prefix=".probe.", dir=folder)
        os.close(descriptor)
        os.unlink(probe)
    except OSError:
        return False
    return True
