"""Nothing lost: special files, concurrent runs, --overwrite, full disks, killed runs' leftovers,
double signals and a reader that goes away (issue 24, "data lost or damaged").

In-process runs use test_cli's `run`; the signal, pipe and concurrency tests run `main.py` for real.
"""

import errno
import json
import os
import signal
import stat
import subprocess
import sys
import threading
import time

import imageio.v2
import pytest

from app import files, outputs
from fem.errors import FemError
from conftest import as_in_a_terminal
from test_cli import ROOT, final_error_line, here, one_error_line, run  # noqa: F401  (here is a fixture)

SMALL_EXPORT = ["export", "cube", "--frames", "3", "--size", "64x64", "--renderer", "software"]


def video_frames(path):
    with imageio.v2.get_reader(path, format="FFMPEG") as reader:
        return reader.count_frames()


def dead_pid():
    """A process id that no process has now."""
    pid = 4_000_000
    while outputs.process_alive(pid):
        pid -= 1
    return pid


# ---------------------------------------------------------------- special files

def test_stats_into_a_fifo_is_streamed_and_the_fifo_stays(here):
    fifo = here / "rows"
    os.mkfifo(fifo)
    received = []
    reader = threading.Thread(target=lambda: received.append(fifo.read_text()))
    reader.start()
    code, out, err = run("simulate", "cube", "--steps", "2", "--stats", str(fifo))
    reader.join(timeout=300)
    assert code == 0, err
    assert stat.S_ISFIFO(os.stat(fifo).st_mode)
    assert [json.loads(line)["step"] for line in received[0].splitlines()] == [1, 2]


@pytest.mark.skipif(os.geteuid() != 0, reason="making a device file needs root")
def test_stats_into_a_character_device_is_not_replaced(here):
    device = here / "mynull"
    os.mknod(device, 0o666 | stat.S_IFCHR, os.makedev(1, 3))        # a copy of /dev/null
    code, out, err = run("simulate", "cube", "--steps", "2", "--stats", str(device))
    assert code == 0, err
    assert stat.S_ISCHR(os.stat(device).st_mode)
    assert sorted(p.name for p in here.iterdir()) == ["mynull"]


def test_a_video_or_folder_that_is_a_special_file_is_refused(here):
    os.mkfifo(here / "v.mp4")
    code, out, err = run(*SMALL_EXPORT, "--out", "o", "--video", "v.mp4")
    assert code == 2
    one_error_line(err, "v.mp4", "not a regular file")
    os.mkfifo(here / "o2")
    code, out, err = run(*SMALL_EXPORT, "--out", "o2")
    assert code == 2 and err.startswith("error: --out o2")
    assert stat.S_ISFIFO(os.stat(here / "v.mp4").st_mode) and stat.S_ISFIFO(os.stat(here / "o2").st_mode)


# ---------------------------------------------------------------- concurrent runs

def test_put_in_place_never_replaces_without_overwrite(tmp_path):
    target = tmp_path / "v.mp4"
    with pytest.raises(FemError, match=r"another run wrote this file.*v-2\.mp4"):
        with files.atomic_open(target, overwrite=False) as f:
            f.write("this run")
            target.write_text("another run")
    assert target.read_text() == "another run"
    assert (tmp_path / "v-2.mp4").read_text() == "this run"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["v-2.mp4", "v.mp4"]


def test_temporary_names_are_this_processs_own(tmp_path):
    with files.atomic_open(tmp_path / "s.jsonl") as f:
        name = os.path.basename(os.readlink(f"/proc/self/fd/{f.fileno()}"))
    assert name.startswith(f".s.jsonl.{os.getpid()}.") and name.endswith(".softfem-part")
    assert files.atomic_path(tmp_path / "v.mp4").name == f".v.mp4.{os.getpid()}.softfem-part.mp4"


def test_a_temporary_name_stays_within_255_bytes_for_any_valid_name(tmp_path):
    name = "é" * 123 + ".mp4"                       # 250 bytes
    assert len(files.atomic_path(tmp_path / name).name.encode()) <= 255
    with files.atomic_open(tmp_path / name) as f:
        f.write("whole")
    assert (tmp_path / name).read_text() == "whole"


def test_an_out_folder_another_export_is_writing_into_is_refused(here):
    (here / "o").mkdir()
    with outputs.FolderLock(here / "o"):            # another run holds it
        code, out, err = run(*SMALL_EXPORT, "--out", "o", "--overwrite")
    assert code == 2
    one_error_line(err, "--out o", "another run is writing into this folder")
    assert list((here / "o").iterdir()) == []


def test_two_exports_at_once_never_claim_each_others_video(tmp_path):
    def start(frames, out):
        return subprocess.Popen([sys.executable, str(ROOT / "main.py"), *SMALL_EXPORT[:2], "--frames", str(frames),
                                 "--size", "64x64", "--out", out, "--video", "v.mp4"],
                                cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)

    runs = {3: start(3, "a"), 4: start(4, "b")}
    results = {frames: (p.wait(timeout=300), *p.communicate()) for frames, p in runs.items()}
    codes = sorted(code for code, _, _ in results.values())
    assert codes == [0, 2], results
    winner = next(frames for frames, (code, _, _) in results.items() if code == 0)
    loser_err = next(err for code, _, err in results.values() if code == 2)
    # Refused up front when the winner had claimed the name already, else when it finishes.
    final_error_line(loser_err, "another run")
    assert video_frames(tmp_path / "v.mp4") == winner
    assert not list(tmp_path.glob(".*part*"))


# ---------------------------------------------------------------- --overwrite

def test_overwrite_replaces_this_exports_frames_and_leaves_everything_else(here):
    out = here / "o"
    out.mkdir()
    (out / "frame_00000.png").write_text("old frame")
    (out / "frame_00009.png").write_text("the user's own")
    (out / "notes.txt").write_text("the user's notes")
    code, stdout, err = run(*SMALL_EXPORT, "--out", "o", "--overwrite")
    assert code == 0, err
    assert (out / "frame_00009.png").read_text() == "the user's own"
    assert (out / "notes.txt").read_text() == "the user's notes"
    assert (out / "frame_00000.png").read_bytes().startswith(b"\x89PNG")
    assert "also holds 1 older frames (frame_00009.png" in err


# ---------------------------------------------------------------- a full disk

class FullDisk:
    """A file object that takes `room` bytes and then fails as a full disk does."""

    def __init__(self, file, room):
        self.file, self.room = file, room

    def write(self, data):
        if len(data) > self.room:
            self.file.write(data[:self.room])           # a write cut short, as on a real disk
            self.room = 0
            raise OSError(errno.ENOSPC, "No space left on device")
        self.room -= len(data)
        return self.file.write(data)

    def __getattr__(self, name):
        return getattr(self.file, name)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.file.close()
        return False


def disk_filling_after(monkeypatch, room, suffix):
    real = os.fdopen

    def fdopen(fd, mode="r", *args, **kwargs):
        file = real(fd, mode, *args, **kwargs)
        name = os.readlink(f"/proc/self/fd/{fd}")
        return FullDisk(file, room) if name.endswith(suffix) else file

    monkeypatch.setattr(files.os, "fdopen", fdopen)


def test_a_full_disk_keeps_the_complete_rows(here, monkeypatch):
    code, out, err = run("simulate", "cube", "--steps", "1", "--stats", "one.jsonl")
    row = len((here / "one.jsonl").read_text())
    disk_filling_after(monkeypatch, int(2.5 * row), ".softfem-part")
    code, out, err = run("simulate", "cube", "--steps", "5", "--stats", "s.jsonl")
    assert code == 2
    final_error_line(err, "s.jsonl", "no space left on device", "kept the 2 complete rows")
    rows = [json.loads(line) for line in (here / "s.jsonl").read_text().splitlines()]
    assert [r["step"] for r in rows] == [1, 2]
    assert sorted(p.name for p in here.iterdir()) == ["one.jsonl", "s.jsonl"]


def test_a_full_disk_keeps_the_complete_frames(here, monkeypatch):
    written = []
    real = files.atomic_open

    def atomic_open(path, *args, **kwargs):
        written.append(path)
        if len(written) == 3:
            raise FemError(f"{path}: no space left on device")
        return real(path, *args, **kwargs)

    from app.commands import export
    monkeypatch.setattr(export, "atomic_open", atomic_open)
    code, out, err = run(*SMALL_EXPORT, "--out", "o", "--video", "v.mp4")
    assert code == 2
    final_error_line(err, "frame_00002.png", "no space left", "kept the 2 complete frames")
    assert sorted(p.name for p in (here / "o").iterdir()) == ["frame_00000.png", "frame_00001.png"]
    assert video_frames(here / "v.mp4") == 2     # the video closed on them


@pytest.fixture
def tiny_disk(tmp_path):
    """A 64 kB tmpfs, where the machine lets this process mount one."""
    disk = tmp_path / "disk"
    disk.mkdir()
    if os.geteuid() != 0 or subprocess.run(["mount", "-t", "tmpfs", "-o", "size=64k", "tmpfs", str(disk)],
                                           capture_output=True).returncode != 0:
        pytest.skip("cannot mount a tmpfs here")
    yield disk
    subprocess.run(["umount", str(disk)], check=True)


def export_onto(disk, *argv):
    return subprocess.run([sys.executable, str(ROOT / "main.py"), "export", "cube", *argv], cwd=disk.parent,
                          capture_output=True, text=True, timeout=600)


@pytest.mark.parametrize("video", ["v.mp4", "v.gif"])
def test_a_video_on_a_full_disk_is_not_put_in_place(tiny_disk, video):
    """The encoder's file is checked before it is renamed: ffmpeg leaves an MP4 with no index
    ("moov atom not found") on a full disk and still exits, Pillow an ENOSPC."""
    run = export_onto(tiny_disk, "--frames", "40", "--size", "640x480", "--out", "o",
                      "--video", str(tiny_disk / video))
    assert run.returncode == 2, run.stderr
    final_error_line(run.stderr, f"{video}: no space left on device", "the video was not written")
    assert "kept the 40 complete frames in o" in run.stderr
    assert list(tiny_disk.iterdir()) == []


def test_frames_and_video_on_one_full_disk_keep_the_frames_and_no_broken_video(tiny_disk):
    run = export_onto(tiny_disk, "--frames", "40", "--size", "640x480", "--out", str(tiny_disk / "o"),
                      "--video", str(tiny_disk / "v.mp4"))
    assert run.returncode == 2, run.stderr
    line = final_error_line(run.stderr, "no space left on device")
    kept = sorted((tiny_disk / "o").iterdir())
    assert kept and f"kept the {len(kept)} complete frames" in line
    for path in kept:
        imageio.v2.imread(path)                    # each one whole
    if (tiny_disk / "v.mp4").exists():            # the encoder finished it on the frames kept
        assert video_frames(tiny_disk / "v.mp4") == len(kept) and f"v.mp4 holds them ({len(kept)} frames)" in line
    else:
        assert "the video was not written" in line
    assert sorted(p.name for p in tiny_disk.iterdir()) in (["o"], ["o", "v.mp4"])


def test_a_dangling_link_as_stats_is_an_existing_file(here):
    os.symlink("gone.jsonl", here / "s.jsonl")
    code, out, err = run("simulate", "cube", "--steps", "1", "--stats", "s.jsonl")
    assert code == 2
    one_error_line(err, "s.jsonl: is a link to gone.jsonl, which does not exist", "--overwrite")
    code, out, err = run("simulate", "cube", "--steps", "1", "--stats", "s.jsonl", "--overwrite")
    assert code == 0, err
    assert not (here / "s.jsonl").is_symlink() and (here / "s.jsonl").read_text().count("\n") == 1


def test_a_video_another_running_export_writes_is_refused_before_any_work(here):
    (here / f".v.mp4.{os.getppid()}.softfem-part.mp4").write_bytes(b"being written")   # a live process's
    code, out, err = run(*SMALL_EXPORT, "--out", "o", "--video", "v.mp4")
    assert code == 2
    one_error_line(err, f"--video v.mp4: another run (process {os.getppid()}) is writing this file")
    assert sorted(p.name for p in here.iterdir()) == [f".v.mp4.{os.getppid()}.softfem-part.mp4"]


def test_a_video_named_as_the_out_folder_is_refused(here):
    code, out, err = run(*SMALL_EXPORT, "--out", "x.mp4", "--video", "x.mp4")
    assert code == 2
    one_error_line(err, "--video x.mp4: is also the --out folder")
    assert list(here.iterdir()) == []


def test_a_real_full_disk_keeps_the_rows_written(tiny_disk):
    run = subprocess.run([sys.executable, str(ROOT / "main.py"), "simulate", "cube", "--steps", "400",
                          "--stats", str(tiny_disk / "s.jsonl")], capture_output=True, text=True, timeout=600)
    assert run.returncode == 2, run.stderr
    assert "no space left on device" in run.stderr and "Traceback" not in run.stderr
    rows = [json.loads(line) for line in (tiny_disk / "s.jsonl").read_text().splitlines()]
    assert rows and [r["step"] for r in rows] == list(range(1, len(rows) + 1))
    assert f"kept the {len(rows)} complete rows" in run.stderr
    assert [p.name for p in tiny_disk.iterdir()] == ["s.jsonl"]


# ---------------------------------------------------------------- what killed runs leave

def test_a_killed_runs_temporary_files_are_removed_and_do_not_block(here):
    pid = dead_pid()
    (here / "o").mkdir()
    (here / "o" / f".frame_00000.png.{pid}.k2j4h1.softfem-part").write_bytes(b"half a frame")
    (here / f".s.jsonl.{pid}.ab12cd.softfem-part").write_text('{"step": 1}\n')
    (here / f".s.jsonl.{os.getpid()}.live.softfem-part").write_text("a run still going")
    (here / f".v.mp4.{pid}.softfem-part.mp4").write_bytes(b"a killed export's video")
    code, out, err = run(*SMALL_EXPORT, "--out", "o", "--video", "v.mp4")
    assert code == 0, err
    assert sorted(p.name for p in (here / "o").iterdir()) == [f"frame_0000{i}.png" for i in range(3)]
    code, out, err = run("simulate", "cube", "--steps", "1", "--stats", "s.jsonl")
    assert code == 0, err
    assert sorted(p.name for p in here.iterdir()) == [f".s.jsonl.{os.getpid()}.live.softfem-part", "o",
                                                      "s-2.jsonl", "s.jsonl", "v.mp4"]
    assert (here / "s-2.jsonl").read_text() == '{"step": 1}\n'        # the killed run's rows are kept


USERS_OWN = [".thesis.2023.part", ".draft.v2.31337.part.txt", ".x.99999999999999999999.part",
             ".x.99999999999999999999.softfem-part", ".frame_00000.png.31337.k2j4h1.part"]


def test_a_users_files_shaped_like_temporary_ones_are_never_removed(here):
    """Only names with this program's marker are a killed run's: a user's `.NAME.NUMBER.part`
    (or a process id no system has) is the user's, kept and counted as the folder's content."""
    (here / "d").mkdir()
    for name in USERS_OWN:
        (here / "d" / name).write_text("notes")
    code, out, err = run(*SMALL_EXPORT, "--out", "d")
    assert code == 2
    one_error_line(err, "d", "folder is not empty")
    code, out, err = run(*SMALL_EXPORT, "--out", "d", "--overwrite")
    assert code == 0, err
    assert all((here / "d" / name).read_text() == "notes" for name in USERS_OWN)


# ---------------------------------------------------------------- signals and pipes

def start(argv, folder, **kwargs):
    kwargs.setdefault("preexec_fn", as_in_a_terminal)
    return subprocess.Popen([sys.executable, str(ROOT / "main.py"), *argv], cwd=folder, stderr=subprocess.PIPE,
                            text=True, **kwargs)


def test_two_sigterms_a_few_ms_apart_still_exit_130(tmp_path):
    process = start(["simulate", "cube86", "--steps", "100000", "--stats", "s.jsonl"], tmp_path,
                    stdout=subprocess.PIPE)
    end = time.monotonic() + 300
    while not any(p.stat().st_size for p in tmp_path.glob(".s.jsonl.*.softfem-part")) and time.monotonic() < end:
        time.sleep(0.05)
    for _ in range(3):
        process.send_signal(signal.SIGTERM)
        time.sleep(0.005)
    out, err = process.communicate(timeout=300)
    assert process.returncode == 130, err
    assert "Traceback" not in err
    assert (tmp_path / "s.jsonl").read_text().count("\n") >= 1


def test_a_reader_that_goes_away_stops_the_run_quietly(tmp_path):
    process = start(["simulate", "cube86", "--steps", "100000", "--stats", "-"], tmp_path, stdout=subprocess.PIPE)
    process.stdout.read(100)
    process.stdout.close()                          # `| head -c 100`
    err = process.stderr.read()
    assert process.wait(timeout=300) == 141, err
    assert "Traceback" not in err and "BrokenPipeError" not in err


def test_an_interrupted_overwriting_export_says_which_frames_are_older(here, monkeypatch):
    out = here / "o"
    out.mkdir()
    for index in range(5):
        (out / f"frame_{index:05d}.png").write_text("an earlier export's frame")
    from app.commands import export
    real, calls = export.write_png, []

    def write_png(*args, **kwargs):
        calls.append(1)
        if len(calls) == 3:
            raise KeyboardInterrupt
        return real(*args, **kwargs)

    monkeypatch.setattr(export, "write_png", write_png)
    code, stdout, err = run(*SMALL_EXPORT, "--out", "o", "--overwrite")
    assert code == 130
    assert "kept the 2 complete frames" in err and "frame_00002.png .. frame_00004.png are older" in err
    assert (out / "frame_00004.png").read_text() == "an earlier export's frame"



@pytest.fixture
def handlers_kept():
    """A real signal leaves SIGTERM and SIGINT ignored after the run (its clean-up must not be
    cut short); put this test process's own handlers back."""
    kept = {s: signal.getsignal(s) for s in files.STOP_SIGNALS}
    yield
    for number, handler in kept.items():
        signal.signal(number, handler)


def test_a_signal_just_after_a_frame_lands_counts_that_frame(here, monkeypatch, handlers_kept):
    """CI once saw 6 frames on disk and "kept the 5 complete frames": the SIGTERM came
    between the frame's rename and the count. The two now move together."""
    from app.commands import export
    real, calls = export.write_png, []

    def write_png(*args, **kwargs):
        real(*args, **kwargs)
        calls.append(1)
        if len(calls) == 2:
            os.kill(os.getpid(), signal.SIGTERM)     # the frame is in place, the count not yet

    monkeypatch.setattr(export, "write_png", write_png)
    code, stdout, err = run(*SMALL_EXPORT, "--out", "o")
    assert code == 130, err
    assert sorted(p.name for p in (here / "o").glob("frame_*.png")) == ["frame_00000.png", "frame_00001.png"]
    assert "kept the 2 complete frames" in err and "older" not in err


def test_a_deferred_signal_goes_to_the_handler_that_was_in_place(handlers_kept):
    """interrupts_deferred hands a signal to interrupt_on_sigterm's handler, which counts it,
    so that later signals during the clean-up are ignored."""
    reached = []
    with pytest.raises(KeyboardInterrupt):
        with files.interrupt_on_sigterm():
            with files.interrupts_deferred():
                os.kill(os.getpid(), signal.SIGTERM)
                time.sleep(0.01)
                reached.append("end of the deferred block")
            reached.append("after it")
    assert reached == ["end of the deferred block"]
    assert signal.getsignal(signal.SIGTERM) == signal.SIG_IGN


def test_a_folder_removed_during_the_run_is_one_error(tmp_path):
    import shutil
    with pytest.raises(FemError, match=r"s\.jsonl: its folder was removed while this run wrote into it"):
        with files.atomic_open(tmp_path / "d" / "s.jsonl") as f:
            f.write("row\n")
            shutil.rmtree(tmp_path / "d")
    assert list(tmp_path.iterdir()) == []
