"""What can go wrong while writing outputs, and how a run keeps the user's data anyway.

- A special file (a device such as /dev/null, a FIFO) given as an output is written to
  as a stream, like `-`, and never replaced by a regular file.
- Temporary files carry this program's marker and the writing process's id
  (`.NAME.PID.xxxx.softfem-part`), so two runs never share one, and a later run can tell the
  leftovers of a killed run (SIGKILL: no clean-up) from those of a run still going, and
  remove them (a killed run's stats rows are kept, under a name of their own); a user's
  own file of a similar name (`.notes.2023.part`) is never touched.
- Without --overwrite a finished file is put in place only if nothing took its name in
  the meantime (a hard link cannot replace a file, a rename can): a run never claims a
  file another run wrote.
- A folder a run writes into is locked (flock on the folder itself), so a second run
  into the same folder is refused instead of mixing its files with the first one's.
- A full disk ends the run with one line naming the file and what was kept.
"""

import errno
import fcntl
import hashlib
import os
import re
import stat
from pathlib import Path

from fem.errors import FemError

# What writing a file can fail with, whatever is written: a full disk, a quota, a file
# too large for the file system, an I/O error, a file system gone read-only.
WRITE_ERRORS = (errno.ENOSPC, errno.EDQUOT, errno.EFBIG, errno.EIO, errno.EROFS)
# Every temporary name of this program ends in this marker (and maybe the output's suffix).
MARKER = "softfem-part"
# .NAME.PID.xxxxxxxx.softfem-part or .NAME.PID.softfem-part.SUFFIX: app.files' temporary
# names. A process id has at most 7 digits (Linux's pid_max is at most 2**22).
TEMPORARY = re.compile(r"\.(?P<name>.+)\.(?P<pid>[1-9]\d{0,6})(\.\w+)?\." + MARKER + r"(\.\w+)?")
# Bytes of the output's name kept in a temporary name: with the rest it stays within the
# 255 bytes a file name may have, however long a valid output name is.
NAME_BYTES = 160
# Hexadecimal digits of a long name's digest in its temporary names.
DIGEST_CHARACTERS = 8
# Seconds by which a process may seem to have started after its file was written (the clock
# set forward meanwhile) and still be taken for its writer.
CLOCK_SLACK = 60.0


def is_special(path) -> bool:
    """True for an existing path that is neither a regular file nor a folder (a character or
    block device, a FIFO, a socket): such a path is written as a stream, never replaced."""
    try:
        mode = os.stat(path).st_mode
    except OSError:
        return False
    return not (stat.S_ISREG(mode) or stat.S_ISDIR(mode))


def names_a_descriptor(path) -> bool:
    """True for /dev/stdout, /dev/fd/N, /proc/self/fd/N, or a link to one of them: a name for
    a file this process already has open, not a place to put a new file."""
    path = Path(path)
    for _ in range(40):                   # a link to a link ...
        if Path(os.path.realpath(path.parent)).match("/proc/*/fd"):
            return True
        if not path.is_symlink():
            return False
        target = Path(os.readlink(path))
        path = target if target.is_absolute() else path.parent / target
    return False


def temporary_stem(name: str) -> str:
    """An output's name as its temporary names carry it: the name itself, or, for a name of more
    than NAME_BYTES bytes, its start and a digest of the whole name, so that two long names that
    start alike still get temporary names of their own (neither run takes the other for a writer
    of its file). Bytes as the file system has them: a name need not be valid UTF-8."""
    data = os.fsencode(name)
    if len(data) <= NAME_BYTES:
        return name
    digest = hashlib.sha256(data).hexdigest()[:DIGEST_CHARACTERS]
    start = data[:NAME_BYTES - DIGEST_CHARACTERS - 1].decode(errors="ignore")   # no half a character
    return f"{start}~{digest}"


def temporary_prefix(path: Path) -> str:
    """The start of this process's temporary names for `path`: '.NAME.PID.'"""
    return f".{temporary_stem(path.name)}.{os.getpid()}."


def process_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:       # someone else's process: alive
        return True
    return True


def process_started(pid: int) -> float | None:
    """When process `pid` started, in seconds since the epoch; None where the system does not
    say (no /proc)."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        boot = next(float(line.split()[1]) for line in Path("/proc/stat").read_text().splitlines()
                    if line.startswith("btime "))
        return boot + int(fields[19]) / os.sysconf("SC_CLK_TCK")     # field 22: start, in ticks since boot
    except (OSError, ValueError, IndexError, StopIteration):
        return None


def writing(path: Path, pid: int) -> bool:
    """True while process `pid` may still be writing its temporary file `path`: it runs, and it
    did not start after the file was last written. After a restart, or once process ids wrap
    around, another process has that id: it is no writer of an old file, which is stale."""
    if not process_alive(pid):
        return False
    started = process_started(pid)
    try:
        written = path.stat().st_mtime
    except OSError:
        return True                   # gone meanwhile: nothing to remove
    return started is None or started < written + CLOCK_SLACK


def temporaries(folder, name=None) -> list[tuple[Path, int]]:
    """[(path, writer's process id)] of this program's temporary files in `folder` (of output
    `name` only, if given)."""
    try:
        entries = list(Path(folder).iterdir())
    except OSError:
        return []
    found = []
    for path in entries:
        match = TEMPORARY.fullmatch(path.name)
        if match and (name is None or match["name"] == temporary_stem(name)):
            found.append((path, int(match["pid"])))
    return found


def stale_temporaries(folder, name=None):
    """The temporary files in `folder` (of output `name` only, if given) whose writer is gone."""
    return [path for path, pid in temporaries(folder, name) if not writing(path, pid)]


def writers_of(path: Path) -> list[int]:
    """The process ids of the other running processes writing the output `path` now."""
    return [pid for temporary, pid in temporaries(path.parent, path.name)
            if pid != os.getpid() and writing(temporary, pid)]


def remove_stale_temporaries(folder, name=None) -> int:
    """Delete what killed runs left in `folder` (a SIGKILL leaves no chance to clean up);
    returns how many files went."""
    removed = 0
    for path in stale_temporaries(folder, name):
        try:
            path.unlink()
            removed += 1
        except OSError:
            pass
    return removed


def rescue_rows(path: Path) -> list[str]:
    """Put the complete rows that killed runs (SIGKILL, the out-of-memory killer: no chance to
    clean up) left under a temporary name for the rows file `path` beside it, under names of
    their own (path-2.jsonl, ...), instead of deleting hours of results; returns a note for each."""
    notes = []
    for temporary, pid in temporaries(path.parent, path.name):
        if writing(temporary, pid):
            continue
        try:
            with open(temporary, "r+b") as f:
                rows = truncate_to_last_line(f.fileno())
                give_usual_permissions(f.fileno())
            if rows:
                kept = free_name(path)
                os.link(temporary, kept)      # fails if the name was taken meanwhile: never replaces
                notes.append(f"note: a run of {path} that was killed (process {pid}) left {rows} complete "
                             f"rows; they are in {kept}")
            os.unlink(temporary)
        except (OSError, FemError):
            pass                              # left where it is: never lost
    return notes


def holds_user_files(folder) -> bool:
    """True when `folder` has anything in it besides this program's temporary files (a killed
    run's, or this run's own; a run still writing into it holds its lock: FolderLock)."""
    ours = {path for path, _ in temporaries(folder)}
    return any(path not in ours for path in Path(folder).iterdir())


def put_in_place(temporary, path, overwrite: bool):
    """Rename the finished `temporary` to `path`. Without overwrite, a file that appeared at
    `path` while this run was writing (another run) is kept, and this run's output goes to
    the first free numbered name beside it, which the FemError names. A folder removed
    during the run (rm -r out/) is a FemError too: what was in it is gone."""
    temporary, path = Path(temporary), Path(path)
    try:
        placed_at(temporary, path, overwrite)
    except FileNotFoundError:
        raise FemError(f"{path}: its folder was removed while this run wrote into it; "
                       "this output went with it") from None


def placed_at(temporary: Path, path: Path, overwrite: bool):
    """put_in_place's renaming: never over another run's file without overwrite."""
    if overwrite:
        os.replace(temporary, path)
        return
    try:
        os.link(temporary, path)              # fails if path exists: never replaces
        os.unlink(temporary)
        return
    except FileExistsError:
        pass
    except FileNotFoundError:
        raise
    except OSError:                           # no hard links here (e.g. FAT): check, then rename
        if not os.path.lexists(path):
            os.replace(temporary, path)
            return
    kept = free_name(path)
    os.replace(temporary, kept)
    raise FemError(f"{path}: another run wrote this file while this one was running; "
                   f"this run's output is in {kept}")


def free_name(path: Path) -> Path:
    """path's stem-2.suffix, -3, ...: the first name not taken."""
    for n in range(2, 10000):
        candidate = path.with_name(f"{path.stem}-{n}{path.suffix}")
        if not os.path.lexists(candidate):
            return candidate
    raise FemError(f"{path}: too many files named {path.stem}-N{path.suffix}")


def open_stream(path, overwrite: bool):
    """Open `path` to write rows into as they come (the window's --stats: `tail -f` follows
    it while the window is open), not under a temporary name. Without overwrite the file
    must not exist (another run may have created it since the check)."""
    mode = "w" if overwrite or is_special(path) else "x"
    try:
        return open(path, mode, buffering=1)
    except FileExistsError:
        raise FemError(f"{path}: file exists; use --overwrite to replace it") from None
    except OSError as error:
        raise write_failed(path, error) from None


def give_usual_permissions(file_descriptor):
    """The permissions a new file gets (rw for all, less the umask): mkstemp makes 0600."""
    umask = os.umask(0)
    os.umask(umask)
    os.fchmod(file_descriptor, 0o666 & ~umask)


def truncate_to_last_line(file_descriptor):
    """Cut a file of text lines back to its last complete line (a full disk can stop a
    write half way through a row); returns the number of complete lines kept."""
    os.lseek(file_descriptor, 0, os.SEEK_SET)
    data = b""
    while chunk := os.read(file_descriptor, 1 << 20):
        data += chunk
    end = data.rfind(b"\n") + 1
    os.ftruncate(file_descriptor, end)
    return data.count(b"\n", 0, end)


def write_failed(path, error: OSError, kept: str = "") -> FemError:
    """The one-line error for an output that could not be written, e.g.
    'out/s.jsonl: no space left on device; kept the 41 complete rows'."""
    reason = "no space left on device" if error.errno in (errno.ENOSPC, errno.EDQUOT) else \
        (error.strerror or str(error)).lower()
    return FemError(f"{path}: {reason}" + (f"; {kept}" if kept else ""))


class FolderLock:
    """An exclusive lock on an output folder for as long as a run writes into it (flock on
    the folder itself: nothing is added to it, and the kernel drops the lock when the
    process ends however it ends). A second run into the same folder gets a FemError."""

    def __init__(self, folder, option="--out"):
        self.folder, self.option = Path(folder), option
        self.descriptor = None

    def __enter__(self):
        self.descriptor = os.open(self.folder, os.O_RDONLY)
        try:
            fcntl.flock(self.descriptor, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(self.descriptor)
            raise FemError(f"{self.option} {self.folder}: another run is writing into this folder; "
                           f"wait for it or choose another folder") from None
        except OSError:
            pass                      # a file system without locks: run unlocked
        return self

    def __exit__(self, *exc):
        os.close(self.descriptor)
        return False

    def removed(self) -> bool:
        """True when the locked folder is no longer at its path (`rm -r out/`, or the working
        folder of a relative path removed; maybe made again since): writing on would make a
        new folder that holds only the later files."""
        locked = os.fstat(self.descriptor)
        try:
            now = os.stat(self.folder)
        except OSError:
            return True
        return (now.st_dev, now.st_ino) != (locked.st_dev, locked.st_ino)
