"""Nothing lost, nothing wrong (issue 37, "data lost or reported wrongly written"): a user's files
that look like temporary ones, a video the encoder could not finish, every signal that ends a run,
a killed export's leftovers, stdout on a full disk, names a temporary name must still fit, and
frame rates no video can store.

Each test checks what a user would check by hand afterwards: which files are there, which are
not, the exit code and the one `error:` line. In-process runs use test_cli's `run`; signals, a
killed run and /dev/full as stdout need `main.py` as a process of its own.
"""

import errno
import json
import os
import signal
import subprocess
import sys
import time

from pathlib import Path

import imageio.v2
import pytest

from app import files, outputs, video
from conftest import as_in_a_terminal
from test_cli import PROGRESS_LINE, ROOT, final_error_line, here, one_error_line, run  # noqa: F401  (here is a fixture)

SMALL_EXPORT = ["export", "cube86", "--frames", "3", "--size", "64x64", "--renderer", "software"]
# A run that lasts until it is stopped: cube86 takes milliseconds a step.
ENDLESS_STATS = ["simulate", "cube86", "--steps", "100000", "--stats", "s.jsonl"]


def main_py(*argv, cwd, stdout):
    """`python main.py ARGV` as a process of its own, run in cwd, writing to stdout: (exit code, stderr)."""
    done = subprocess.run([sys.executable, str(ROOT / "main.py"), *argv], cwd=cwd, stdout=stdout,
                          stderr=subprocess.PIPE, text=True, timeout=300)
    return done.returncode, done.stderr


def start(argv, folder, **kwargs):
    """`main.py argv` in folder, getting the signals a terminal sends unless kwargs say otherwise."""
    kwargs.setdefault("preexec_fn", as_in_a_terminal)
    return subprocess.Popen([sys.executable, str(ROOT / "main.py"), *argv], cwd=folder,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, **kwargs)


def wait_for(condition, process, seconds=300):
    end = time.monotonic() + seconds
    while not condition() and process.poll() is None and time.monotonic() < end:
        time.sleep(0.05)
    assert condition(), "the run ended before it got there"


def wait_until_no_process_names(text, seconds=120):
    """Until no running process has `text` in its command line (Linux: /proc; elsewhere at once)."""
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        lines = []
        for entry in Path("/proc").glob("[0-9]*/cmdline"):
            try:
                lines.append(entry.read_bytes())
            except OSError:
                pass
        if not any(text.encode() in line for line in lines):
            return
        time.sleep(0.1)


def video_frames(path):
    with imageio.v2.get_reader(path, format="FFMPEG") as reader:
        return reader.count_frames()


def pngs(folder):
    return sorted(p.name for p in folder.glob("frame_*.png"))


def temporaries_left(folder):
    """This program's temporary files in folder and below."""
    return sorted(p.name for p in folder.rglob("*") if outputs.TEMPORARY.fullmatch(p.name))


# ---------------------------------------------------------------- a user's files are never removed

USERS_OWN = [".thesis.2023.part", ".draft.v2.31337.part.txt", ".x.99999999999999999999.part",
             ".v.mp4.99999999999999999999.softfem-part.mp4", ".v.mp4.31337.part.mp4"]


def test_files_shaped_like_temporary_ones_beside_the_video_are_kept(here):
    """The issue's reproduction: `.thesis.2023.part` and `.draft.v2.31337.part.txt` went, and a
    process id of 20 digits was an OverflowError. Only this program's marker makes a file its own."""
    (here / "d").mkdir()
    for name in USERS_OWN:
        (here / "d" / name).write_text("notes")
    code, out, err = run(*SMALL_EXPORT, "--out", "d", "--video", "d/v.mp4", "--overwrite")
    assert code == 0, err
    assert all((here / "d" / name).read_text() == "notes" for name in USERS_OWN)
    assert pngs(here / "d") == [f"frame_0000{i}.png" for i in range(3)] and video_frames(here / "d" / "v.mp4") == 3
    assert temporaries_left(here) == []


def test_a_killed_exports_temporary_video_is_removed_by_the_next_export(here):
    process = start([*SMALL_EXPORT, "--frames", "100000", "--out", "first", "--video", "v.mp4"], here)
    wait_for(lambda: pngs(here / "first"), process)
    leftover = here / f".v.mp4.{process.pid}.{outputs.MARKER}.mp4"
    assert leftover.exists()
    process.kill()                                   # SIGKILL: no chance to clean up
    process.wait(timeout=300)
    assert leftover.exists() and not (here / "v.mp4").exists()
    # its encoder, an ffmpeg child, outlives it until it has read the closed pipe and finished the
    # file, which it opens again by name to move the index to the front: under load that came after
    # the next export's cleanup and put the file back. A later export removes it then.
    wait_until_no_process_names(leftover.name)
    code, out, err = run(*SMALL_EXPORT, "--out", "second", "--video", "v.mp4")
    assert code == 0, err
    assert not leftover.exists() and video_frames(here / "v.mp4") == 3


def test_a_killed_runs_rows_are_kept_by_the_next_run(here):
    """SIGKILL (or the out-of-memory killer) leaves the rows under the temporary name; the next
    run to the same file deleted them silently."""
    process = start(ENDLESS_STATS, here)

    def hidden():
        return [p for p in here.glob(f".s.jsonl.{process.pid}.*{outputs.MARKER}") if p.stat().st_size]

    wait_for(hidden, process)
    process.kill()
    process.wait(timeout=300)
    left = hidden()[0].read_text()
    complete = left[:left.rfind("\n") + 1]
    code, out, err = run("simulate", "cube86", "--steps", "2", "--stats", "s.jsonl")
    assert code == 0, err
    rows = complete.count("\n")
    assert (f"note: a run of s.jsonl that was killed (process {process.pid}) left {rows} complete rows; "
            "they are in s-2.jsonl") in err.splitlines()
    assert (here / "s-2.jsonl").read_text() == complete and (here / "s.jsonl").read_text().count("\n") == 2
    assert sorted(p.name for p in here.iterdir()) == ["s-2.jsonl", "s.jsonl"]


@pytest.mark.skipif(not os.path.exists("/proc/self/stat"), reason="no /proc: a process's start is not known")
def test_a_leftover_whose_process_id_another_process_has_now_is_stale(here):
    """After a restart, a killed export's `.v.mp4.PID...` named a process id some other program
    had by then: "another run (process PID) is writing this file", for as long as it ran."""
    other = subprocess.Popen(["sleep", "120"])                     # started after the leftover was written
    try:
        leftover = here / f".v.mp4.{other.pid}.{outputs.MARKER}.mp4"
        leftover.write_bytes(b"half a video")
        an_hour_ago = time.time() - 3600
        os.utime(leftover, (an_hour_ago, an_hour_ago))
        code, out, err = run(*SMALL_EXPORT, "--out", "o", "--video", "v.mp4")
    finally:
        other.kill()
        other.wait()
    assert code == 0, err
    assert not leftover.exists() and video_frames(here / "v.mp4") == 3


# ---------------------------------------------------------------- a video the encoder could not finish

def test_an_mp4_the_encoder_left_without_its_index_is_not_put_in_place(here, monkeypatch):
    """ffmpeg on a full disk leaves an MP4 with no index ("moov atom not found") and still
    exits normally: the export said "wrote v.mp4", exit 0."""
    real = video.imageio.v2.get_writer

    def get_writer(path, **kwargs):
        writer = real(path, **kwargs)
        close = writer.close

        def close_on_a_full_disk():
            close()
            os.truncate(path, os.path.getsize(path) // 2)      # the index at the end never landed
        writer.close = close_on_a_full_disk
        return writer

    monkeypatch.setattr(video.imageio.v2, "get_writer", get_writer)
    code, out, err = run(*SMALL_EXPORT, "--out", "o", "--video", "v.mp4")
    assert code == 2
    final_error_line(err, "v.mp4: ", "the video was not written", "kept the 3 complete frames in o")
    assert pngs(here / "o") == [f"frame_0000{i}.png" for i in range(3)]
    assert sorted(p.name for p in here.iterdir()) == ["o"]


def test_a_gif_on_a_full_disk_is_one_error_and_no_file(here, monkeypatch):
    """Pillow's ENOSPC was a traceback."""
    def save_on_a_full_disk(self):
        self.path.write_bytes(b"GIF89a half a picture")
        raise OSError(errno.ENOSPC, "No space left on device", str(self.path))

    monkeypatch.setattr(video.GifWriter, "close", save_on_a_full_disk)
    code, out, err = run(*SMALL_EXPORT, "--out", "o", "--video", "v.gif")
    assert code == 2
    final_error_line(err, "v.gif: no space left on device; the video was not written; kept the 3 complete frames")
    assert "Traceback" not in err
    assert sorted(p.name for p in here.iterdir()) == ["o"] and len(pngs(here / "o")) == 3


# ---------------------------------------------------------------- every signal that ends a run

STOPPING = ["SIGHUP", "SIGQUIT", "SIGUSR1", "SIGUSR2", "SIGALRM", "SIGXCPU"]


@pytest.mark.parametrize("name", STOPPING)
def test_every_stopping_signal_keeps_the_rows_in_the_real_file(tmp_path, name):
    """SIGHUP, SIGQUIT or SIGUSR1 left the rows only in a hidden .part file."""
    process = start(ENDLESS_STATS, tmp_path)
    wait_for(lambda: any(p.stat().st_size for p in tmp_path.glob(f".s.jsonl.*{outputs.MARKER}")), process)
    process.send_signal(getattr(signal, name))
    err = process.communicate(timeout=300)[1]
    assert process.returncode == 130, err
    rows = [json.loads(line) for line in (tmp_path / "s.jsonl").read_text().splitlines()]
    assert rows and [r["step"] for r in rows] == list(range(1, len(rows) + 1))
    assert f"kept its {len(rows)} complete rows in s.jsonl" in err and "Traceback" not in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s.jsonl"]


@pytest.fixture
def handlers_kept():
    """A signal leaves the stopping signals ignored after the run (its clean-up must not be cut
    short); put this test process's own handlers back."""
    kept = {s: signal.getsignal(s) for s in files.STOP_SIGNALS}
    yield
    for number, handler in kept.items():
        signal.signal(number, handler)


def test_a_signal_while_the_rows_are_put_in_place_keeps_them(here, monkeypatch, handlers_kept):
    """A SIGTERM between the last row and the rename removed the complete temporary file."""
    real = outputs.put_in_place

    def put_in_place(*args):
        os.kill(os.getpid(), signal.SIGTERM)
        real(*args)

    monkeypatch.setattr(outputs, "put_in_place", put_in_place)
    code, out, err = run("simulate", "cube86", "--steps", "2", "--stats", "s.jsonl")
    assert code == 130, err
    *progress, last = err.strip().splitlines()
    assert last == "interrupted after its last step; kept its 2 complete rows in s.jsonl"
    assert all(PROGRESS_LINE.fullmatch(line) for line in progress), err
    assert (here / "s.jsonl").read_text().count("\n") == 2 and temporaries_left(here) == []


def test_a_run_started_with_sighup_ignored_goes_on_after_one(tmp_path):
    """`nohup main.py ...`: closing the terminal must not stop the run (it did: exit 130)."""
    steps = 300
    process = start([*ENDLESS_STATS[:3], str(steps), *ENDLESS_STATS[4:]], tmp_path,
                    preexec_fn=lambda: signal.signal(signal.SIGHUP, signal.SIG_IGN))
    wait_for(lambda: any(p.stat().st_size for p in tmp_path.glob(f".s.jsonl.*{outputs.MARKER}")), process)
    process.send_signal(signal.SIGHUP)
    err = process.communicate(timeout=300)[1]
    assert process.returncode == 0, err
    assert (tmp_path / "s.jsonl").read_text().count("\n") == steps


@pytest.mark.parametrize("name", ["SIGINT", "SIGHUP"])
def test_an_interrupted_export_keeps_as_many_frames_in_the_video_as_pngs(tmp_path, name):
    """Ctrl-C kept 122 PNGs and said the video had 121 frames."""
    process = start([*SMALL_EXPORT, "--frames", "100000", "--out", "o", "--video", "v.mp4"], tmp_path)
    wait_for(lambda: len(pngs(tmp_path / "o")) >= 3, process)
    process.send_signal(getattr(signal, name))
    err = process.communicate(timeout=300)[1]
    assert process.returncode == 130, err
    kept = len(pngs(tmp_path / "o"))
    assert f"kept the {kept} complete frames" in err and f"v.mp4 with {kept} frames" in err
    assert video_frames(tmp_path / "v.mp4") == kept
    assert temporaries_left(tmp_path) == []


# ---------------------------------------------------------------- stdout on a full disk

@pytest.mark.parametrize("argv", [["simulate", "cube86", "--steps", "2"], ["simulate", "cube86", "--steps", "2",
                                                                          "--stats", "-"],
                                  ["scenes"], ["help"], ["help", "export"], ["export", "-h"], ["--version"]],
                         ids=" ".join)
def test_stdout_on_a_full_disk_is_one_error(tmp_path, argv):
    """ENOSPC was a traceback (simulate, scenes, export, --version), or help lost with exit 0."""
    with open("/dev/full", "w") as full:
        code, err = main_py(*argv, cwd=tmp_path, stdout=full)
    assert code == 2, err
    final_error_line(err, "error: standard output: no space left on device")   # found when the summary is written
    assert list(tmp_path.iterdir()) == []


def test_an_export_with_stdout_on_a_full_disk_keeps_its_frames(tmp_path):
    with open("/dev/full", "w") as full:
        code, err = main_py(*SMALL_EXPORT, "--out", "o", "--video", "v.mp4", cwd=tmp_path, stdout=full)
    assert code == 2, err
    final_error_line(err, "error: standard output: no space left on device")
    assert len(pngs(tmp_path / "o")) == 3 and video_frames(tmp_path / "v.mp4") == 3


@pytest.mark.skipif(not os.path.islink("/dev/stdout"), reason="/dev/stdout is not a link to /proc here")
@pytest.mark.parametrize("name", ["/dev/stdout", "/dev/fd/1", "link"])
def test_stats_into_a_redirected_stdout_is_refused_and_dev_stdout_stays(tmp_path, name):
    """`--stats /dev/stdout > log.txt` said "file exists; use --overwrite", and with --overwrite
    (as root) would have put a file of its own in place of /dev/stdout."""
    os.symlink("/dev/stdout", tmp_path / "link")
    with open(tmp_path / "log.txt", "w") as log:
        code, err = main_py("simulate", "cube86", "--steps", "1", "--stats", name, cwd=tmp_path, stdout=log)
    assert code == 2, err
    one_error_line(err, f"--stats {name}: is a file this run already has open", "give - for standard output")
    assert os.path.islink("/dev/stdout") and os.readlink(tmp_path / "link") == "/dev/stdout"
    assert (tmp_path / "log.txt").read_text() == ""


def test_stats_on_a_full_disk_is_one_error():
    code, out, err = run("simulate", "cube86", "--steps", "2", "--stats", "/dev/full")
    assert code == 2
    final_error_line(err, "/dev/full: no space left on device")


# ---------------------------------------------------------------- names

def test_a_250_character_video_name_is_written(here):
    """Its temporary name passed 255 bytes: Broken pipe."""
    name = "v" * 246 + ".mp4"
    code, out, err = run(*SMALL_EXPORT, "--out", "o", "--video", name)
    assert code == 0, err
    assert video_frames(here / name) == 3 and temporaries_left(here) == []


def test_two_long_video_names_that_start_alike_are_not_taken_for_one(here):
    """Cut to the same first bytes, another export's video looked like this one's writer."""
    writing, name = "v" * 200 + "-first.mp4", "v" * 200 + "-second.mp4"
    other = here / f".{outputs.temporary_stem(writing)}.{os.getppid()}.{outputs.MARKER}.mp4"   # a live process's
    other.write_bytes(b"being written")
    code, out, err = run(*SMALL_EXPORT, "--out", "o", "--video", name)
    assert code == 0, err
    assert video_frames(here / name) == 3 and other.read_bytes() == b"being written"


def test_output_names_that_are_not_utf8_are_written(here):
    """A name of raw bytes (b'\\xff') was a UnicodeEncodeError."""
    stats, clip = os.fsdecode(b"s\xff.jsonl"), os.fsdecode(b"v\xff.mp4")
    code, out, err = run("simulate", "cube86", "--steps", "2", "--stats", stats)
    assert code == 0, err
    code, out, err = run(*SMALL_EXPORT, "--out", "o", "--video", clip)
    assert code == 0, err
    assert (here / stats).read_text().count("\n") == 2 and video_frames(here / clip) == 3


@pytest.mark.parametrize("option", ["--stats", "--video"])
def test_a_dangling_link_as_an_output_is_refused_and_kept(here, option):
    """It gave a false "another run wrote this file while this one was running"."""
    name = "s.jsonl" if option == "--stats" else "v.mp4"
    os.symlink("gone", here / name)
    argv = ["simulate", "cube86", "--steps", "1"] if option == "--stats" else [*SMALL_EXPORT, "--out", "o"]
    code, out, err = run(*argv, option, name)
    assert code == 2
    one_error_line(err, f"{name}: is a link to gone, which does not exist", "--overwrite")
    assert "another run" not in err
    assert os.readlink(here / name) == "gone" and sorted(p.name for p in here.iterdir()) == [name]


def test_a_video_named_as_the_out_folder_is_refused_before_any_work(here):
    code, out, err = run(*SMALL_EXPORT, "--out", "x.mp4", "--video", "x.mp4")
    assert code == 2
    one_error_line(err, "--video x.mp4: is also the --out folder")
    assert "another run" not in err and list(here.iterdir()) == []


# ---------------------------------------------------------------- frame rates

@pytest.mark.parametrize("rate, video_name, said", [
    (["--fps", "1e300"], "v.mp4", "--fps 1e+300"),                       # was Broken pipe
    (["--speed", "1e-300"], "v.mp4", "--speed: the video would play at"),    # was Broken pipe
    (["--fps", "1e-5", "--steps-per-frame", "1"], "v.gif", "--fps 1e-05"),   # was OverflowError
    (["--fps", "1e-5", "--steps-per-frame", "1"], "v.mp4", "--fps 1e-05"),   # was a video with no stream
    (["--fps", "0.004", "--steps-per-frame", "1"], "v.mp4", "--fps 0.004"),
])
def test_a_frame_rate_no_video_can_store_is_refused_before_any_work(here, rate, video_name, said):
    code, out, err = run(*SMALL_EXPORT, *rate, "--out", "o", "--video", video_name)
    assert code == 2
    one_error_line(err, said, "frames per second")
    assert not (here / video_name).exists() and pngs(here / "o") == [] and temporaries_left(here) == []


def test_the_default_frame_rate_is_what_help_says(here):
    """`help export` said "about 30"; every export played at 25."""
    code, out, err = run("help", "export")
    assert code == 0 and "25 at the usual dt of 0.02 s" in " ".join(out.split())
    code, out, err = run(*SMALL_EXPORT, "--out", "o", "--video", "v.mp4")
    assert code == 0, err
    assert "the video plays at 25 frames per second" in out
    with imageio.v2.get_reader(here / "v.mp4", format="FFMPEG") as reader:
        assert reader.get_meta_data()["fps"] == 25
