"""Writing files without ever losing a user's data.

Every output goes to a temporary name in the same folder and is renamed into
place when complete, so an interrupted run leaves only whole files; nothing
existing is replaced unless the user said --overwrite. Where an output will
go is checked before any work starts (`check_output`), so a run never
computes for minutes and then fails to save.
"""

import contextlib
import os
import signal
import tempfile
from pathlib import Path

from app import outputs
from fem.errors import FemError


def refuse_overwrite(path, overwrite, flag="--overwrite"):
    """FemError if `path` exists (a file) or is a non-empty folder and overwrite is off.
    A special file (/dev/null, a FIFO) is streamed to, not replaced, so it is no obstacle;
    the temporary files of a killed run do not make a folder non-empty."""
    path = Path(path)
    if overwrite or outputs.is_special(path):
        return
    if path.is_dir() and outputs.holds_user_files(path):
        raise FemError(f"{path}: folder is not empty; use {flag} to write into it anyway")
    if path.is_file():
        raise FemError(f"{path}: file exists; use {flag} to replace it")
    if path.is_symlink() and not path.exists():
        raise FemError(f"{path}: is a link to {os.readlink(path)}, which does not exist; "
                       f"use {flag} to replace the link")


def check_output(path, option, kind):
    """FemError unless `path` can be written as a `kind` ("file" or "folder"), the value of
    command-line `option` (named in the message).

    Catches, before any work: a file where a folder must be (`afile/sub`), a folder
    given as a file name, /dev/stdout redirected to a file, and a place where no file
    can be created (read-only file system, /proc, no permission), by creating and
    removing a probe file in the deepest folder that exists on the way.
    """
    path = Path(path)
    where = f"{option} {path}"
    if kind == "file" and outputs.is_special(path):
        return                    # written as a stream (atomic_open)
    if kind == "file" and outputs.names_a_descriptor(path):
        # A redirection (`> log.txt`): a file of its own would replace /dev/stdout itself.
        raise FemError(f"{where}: is a file this run already has open (a redirection to a regular file); "
                       "give - for standard output, or the file's own name")
    if kind == "file" and path.is_dir():
        raise FemError(f"{where}: is a folder; give a file name")
    folder = path if kind == "folder" else path.parent
    existing = folder
    while not existing.exists() and existing != existing.parent:
        existing = existing.parent
    if not existing.is_dir():
        raise FemError(f"{where}: {existing} is a file, not a folder")
    try:
        descriptor, probe = tempfile.mkstemp(prefix=".probe.", dir=existing)
        os.close(descriptor)
        os.unlink(probe)
    except OSError as error:
        raise FemError(f"{where}: cannot create files in {existing} ({error.strerror})") from None


@contextlib.contextmanager
def atomic_open(path, mode="w", keep_if_interrupted=False, overwrite=True, make_folder=True):
    """Open a temporary file beside `path`; on success it replaces `path`, on error it vanishes.

    keep_if_interrupted: for a stream of complete records (one JSON row per line,
    each written with one call): on Ctrl-C or SIGTERM (KeyboardInterrupt) what was
    written so far still replaces `path`, so an interrupted run keeps its rows, and on
    a full disk the complete rows are kept as well (FemError saying so).
    overwrite: False puts the file in place only if no other run created `path` meanwhile
    (app.outputs.put_in_place). A special file (/dev/null, a FIFO) is opened and written
    directly, never replaced. make_folder: False for a folder that must still be the one the
    run made (an export's frames): gone, it is not made again.
    """
    path = Path(path)
    if outputs.is_special(path):
        yield from _stream(path, mode)
        return
    if make_folder and not path.parent.is_dir():
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            raise FemError(f"{path.parent}: cannot create folder: {e.strerror}") from None
    try:
        fd, tmp = tempfile.mkstemp(prefix=outputs.temporary_prefix(path), suffix=f".{outputs.MARKER}",
                                    dir=path.parent)
    except FileNotFoundError:             # the folder (or the working folder) was removed meanwhile
        raise FemError(f"{path}: its folder was removed while this run wrote into it") from None

    def put_in_place():
        # A signal now would leave the complete file under its temporary name, then remove it.
        with interrupts_deferred():
            outputs.give_usual_permissions(fd)
            outputs.put_in_place(tmp, path, overwrite)

    try:
        try:
            with os.fdopen(fd, mode, closefd=False) as f:
                yield f
        except KeyboardInterrupt:
            if keep_if_interrupted:
                put_in_place()
            raise
        except OSError as error:
            if error.errno not in outputs.WRITE_ERRORS:
                raise
            if not keep_if_interrupted:
                raise outputs.write_failed(path, error) from None
            rows = outputs.truncate_to_last_line(fd)
            put_in_place()
            raise outputs.write_failed(path, error, f"kept the {rows} complete rows written before") from None
        put_in_place()
    finally:
        os.close(fd)
        with contextlib.suppress(OSError):
            os.unlink(tmp)


def _stream(path, mode):
    """Write straight into a special file (a device, a FIFO), as to stdout; a device that
    takes nothing (/dev/full) is a FemError."""
    try:
        f = open(path, mode, buffering=1 if "b" not in mode else -1)   # each row as it comes
    except OSError as error:
        raise FemError(f"{path}: cannot write ({error.strerror})") from None
    try:
        with f:
            yield f
    except OSError as error:
        if error.errno not in outputs.WRITE_ERRORS:
            raise
        raise outputs.write_failed(path, error) from None


def atomic_path(path):
    """A temporary path beside `path` keeping its suffix (for writers that want a file name),
    this process's own; call app.outputs.put_in_place(tmp, path, overwrite) when it is complete."""
    path = Path(path)
    return path.with_name(f"{outputs.temporary_prefix(path)}{outputs.MARKER}{path.suffix}")


def claim(path, option) -> Path:
    """This run's temporary file for `path` (atomic_path's name), made now, after checking that
    no other running process writes `path`: a second export of the same video is refused before
    its work, not after. (Two runs starting at the same moment may both pass; the one that
    finishes second then keeps its output under another name: outputs.put_in_place.)"""
    path = Path(path)
    others = outputs.writers_of(path)
    if others:
        raise FemError(f"{option} {path}: another run (process {others[0]}) is writing this file; "
                       "wait for it or choose another name")
    path.parent.mkdir(parents=True, exist_ok=True)
    temporary = atomic_path(path)
    temporary.touch()
    return temporary


def numbered_path(folder, stem: str, suffix: str) -> Path:
    """folder/stem-001.suffix, stem-002.suffix, ...: the first name not taken."""
    for n in range(1, 10000):
        path = Path(folder) / f"{stem}-{n:03d}{suffix}"
        if not path.exists():
            return path
    raise FemError(f"too many files named {stem}-NNN{suffix} in {folder}")


@contextlib.contextmanager
def signals_handled(signals, handler, afterwards=None):
    """Inside the block, `handler(signum, frame)` handles each of `signals` that is not ignored;
    afterwards the previous handlers, which the block receives as {signal: handler}, are back, or
    what `afterwards()` returns where it returns a handler (straight from `handler` to it: no signal
    meets the previous one between). An ignored signal stays ignored: `nohup` ignores SIGHUP so that
    closing the terminal does not stop the run. Off the main thread signals stay as they are (and the
    block receives {})."""
    try:
        previous = {s: signal.signal(s, handler) for s in signals if signal.getsignal(s) != signal.SIG_IGN}
    except ValueError:            # not the main thread
        yield {}
        return
    try:
        yield previous
    finally:
        after = afterwards() if afterwards else None
        for s, old in previous.items():
            signal.signal(s, old if after is None else after)


# What stops a run as Ctrl-C does: a killed job or cancelled CI step (SIGTERM), a closed
# terminal (SIGHUP), Ctrl-\ (SIGQUIT), a CPU-time limit reached (SIGXCPU: `ulimit -t`, batch
# queues), `kill -USR1`, `-USR2` or `-ALRM`: the signals sent to end a run, whose default would
# end it with nothing saved. (SIGKILL cannot be caught.)
STOP_SIGNALS = [signal.SIGINT, signal.SIGTERM, signal.SIGHUP, signal.SIGQUIT, signal.SIGUSR1, signal.SIGUSR2,
                signal.SIGALRM, signal.SIGXCPU]


@contextlib.contextmanager
def interrupt_on_sigterm():
    """Treat SIGTERM and the other STOP_SIGNALS like Ctrl-C, so that a run stops the
    same way: complete files kept, temporary ones removed, exit code 130.

    Only the first of them interrupts; later ones (a second signal a few ms
    after the first, while the run is already stopping) are ignored, here and after
    the block, so that they cannot cut the clean-up short or change the exit code."""
    arrived = []

    def interrupt(signum, frame):
        arrived.append(signum)
        if len(arrived) == 1:
            raise KeyboardInterrupt

    # once one arrived, each goes from `interrupt` straight to ignored: through its default in between, a
    # third SIGTERM 10 ms after the first ended the run by the signal (-15), not 130 (a CI run, 2026-12-03)
    with signals_handled(STOP_SIGNALS, interrupt, lambda: signal.SIG_IGN if arrived else None):
        yield


@contextlib.contextmanager
def interrupts_deferred():
    """Ctrl-C, SIGTERM or another of STOP_SIGNALS arriving inside the block takes effect when it
    ends: a video frame half sent to the encoder, or a container half closed, would leave a file no
    player can open."""
    arrived = []
    with signals_handled(STOP_SIGNALS, lambda signum, frame: arrived.append(signum)) as outer:
        yield
    if arrived:
        # Hand the signal to the handler that was in place (interrupt_on_sigterm's counts it).
        handler = outer.get(arrived[0])
        if callable(handler):
            handler(arrived[0], None)
        elif handler != signal.SIG_IGN:
            raise KeyboardInterrupt
