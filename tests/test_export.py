"""`main.py export`: the checks one would do by hand on an export folder.

Each export runs as its own process, as a user would run it: small frames, few
frames and the small cube86 scene keep the whole module under a minute on two cores.
"""

import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest
from PIL import Image

from conftest import as_in_a_terminal
from test_cli import final_error_line

REPO = Path(__file__).resolve().parents[1]
FRAMES = 4
SIZE = (160, 128)   # multiples of 16, as H.264 wants
MS = r"\d+\.\d ms"
EXPORT = ["cube86", "--frames", str(FRAMES), "--size", f"{SIZE[0]}x{SIZE[1]}", "--steps-per-frame", "3"]


def export(*args, cwd, env=None, **popen):
    """`python main.py export ...` in a fresh interpreter, run from a temporary
    folder (GGUI writes an imgui.ini into the working directory)."""
    command = [sys.executable, str(REPO / "main.py"), "export", *args]
    return subprocess.run(command, cwd=cwd, capture_output=True, text=True, timeout=300,
                          env={**os.environ, **(env or {})}, **popen)


def frames(folder):
    return sorted(Path(folder).glob("frame_*.png"))


def coral(image):
    """Mask (H, W) of pixels of the first body's colour (coral), lit or in shade."""
    rgb = image.astype(int)
    return (rgb[..., 0] > rgb[..., 1] + 40) & (rgb[..., 1] > rgb[..., 2])


@pytest.fixture(scope="module")
def workdir(tmp_path_factory):
    return tmp_path_factory.mktemp("export")


@pytest.fixture(scope="module")
def first(workdir):
    """An export with an MP4, through the default renderer (the software one)."""
    result = export(*EXPORT, "--out", "a", "--video", "a.mp4", cwd=workdir)
    assert result.returncode == 0, result.stderr
    return result


def test_export_writes_n_pictures_and_a_video_of_n_frames(workdir, first):
    pngs = frames(workdir / "a")
    assert [p.name for p in pngs] == [f"frame_{i:05d}.png" for i in range(FRAMES)]
    for path in pngs:
        image = np.asarray(Image.open(path).convert("RGB"))
        assert image.shape == (SIZE[1], SIZE[0], 3)
        assert coral(image).sum() > 50, f"{path.name}: the soft cube is not in the picture"
        assert len(np.unique(image.reshape(-1, 3), axis=0)) > 100, f"{path.name} is blank"
    video = list(iio.imiter(workdir / "a.mp4", plugin="FFMPEG"))
    assert len(video) == FRAMES
    assert video[0].shape == (SIZE[1], SIZE[0], 3)
    # Real time: 3 steps of 0.02 s per frame play at 1 / 0.06 frames per second.
    assert iio.immeta(workdir / "a.mp4", plugin="FFMPEG")["fps"] == pytest.approx(1 / 0.06, rel=1e-3)
    # stderr is not a terminal here: no progress bar redrawn with carriage returns.
    assert "\r" not in first.stderr
    # The last line on stdout says where the files are; the one before, where the time went.
    lines = first.stdout.strip().splitlines()
    assert lines[-1].endswith("a.mp4")
    timing = next(line for line in lines if line.startswith(f"{FRAMES} frames"))
    assert re.fullmatch(rf"{FRAMES} frames, 3 steps/frame: simulation {MS}/frame \({MS}/step\), rendering "
                        rf"{MS}/frame \(software\), waiting for the writer {MS}/frame \(it wrote each frame in "
                        rf"{MS}, beside the loop\)", timing), timing
    assert not list(workdir.glob("**/*softfem-part*"))


def test_same_arguments_give_byte_identical_pictures(workdir, first):
    again = export(*EXPORT, "--out", "b", cwd=workdir)
    assert again.returncode == 0, again.stderr
    for a, b in zip(frames(workdir / "a"), frames(workdir / "b"), strict=True):
        assert a.read_bytes() == b.read_bytes(), a.name


def test_the_default_renderer_needs_no_vulkan(workdir, first):
    result = export(*EXPORT, "--out", "soft", cwd=workdir, env={"VK_ICD_FILENAMES": "/nonexistent"})
    assert result.returncode == 0, result.stderr
    assert "GGUI" not in result.stderr and "(software)" in result.stderr + result.stdout
    for a, b in zip(frames(workdir / "a"), frames(workdir / "soft"), strict=True):
        assert a.read_bytes() == b.read_bytes(), a.name


def test_ggui_renderer_draws_the_same_scene(workdir, first):
    result = export(*EXPORT, "--out", "ggui", "--renderer", "ggui", cwd=workdir)
    if result.returncode != 0:
        assert result.returncode == 2, result.stderr
        final_error_line(result.stderr, "--renderer ggui")
        pytest.skip(f"GGUI cannot open here: {result.stderr.strip()}")
    assert "(ggui)" in result.stderr + result.stdout
    last = np.asarray(Image.open(frames(workdir / "ggui")[-1]).convert("RGB"))
    reference = np.asarray(Image.open(frames(workdir / "a")[-1]).convert("RGB"))
    # The two back ends draw the same triangles: the cube covers the same pixels.
    overlap = (coral(last) & coral(reference)).sum() / (coral(last) | coral(reference)).sum()
    assert overlap > 0.9


def test_compare_shows_a_linear_and_a_corotational_copy(workdir):
    result = export(*EXPORT, "--compare", "--out", "c", "--video", "c.gif", cwd=workdir)
    assert result.returncode == 0, result.stderr
    image = np.asarray(Image.open(frames(workdir / "c")[-1]).convert("RGB"))
    columns = np.flatnonzero(coral(image).any(axis=0))
    half = SIZE[0] // 2
    left, right = columns[columns < half], columns[columns >= half]
    # The soft cube once in each half, with empty columns between the two copies.
    assert len(left) > 5 and len(right) > 5
    assert right.min() - left.max() > 10
    assert len(list(iio.imiter(workdir / "c.gif"))) == FRAMES


def test_refuses_a_non_empty_folder(workdir):
    folder = workdir / "taken"
    folder.mkdir()
    (folder / "notes.txt").write_text("mine")
    result = export(*EXPORT, "--out", "taken", cwd=workdir)
    assert result.returncode == 2
    assert result.stderr.count("\n") == 1 and result.stderr.startswith("error: ")
    assert [p.name for p in folder.iterdir()] == ["notes.txt"]


def test_interrupted_export_keeps_its_frames_and_a_video_of_them(workdir):
    command = [sys.executable, str(REPO / "main.py"), "export", "cube86", "--frames", "1000",
               "--size", "160x128", "--out", "cut", "--video", "cut.mp4"]
    process = subprocess.Popen(command, cwd=workdir, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                               text=True, preexec_fn=as_in_a_terminal)
    deadline = time.monotonic() + 300
    while len(frames(workdir / "cut")) < 3 and process.poll() is None and time.monotonic() < deadline:
        time.sleep(0.05)
    process.send_signal(signal.SIGTERM)
    stderr = process.communicate(timeout=300)[1]
    assert process.returncode == 130, stderr
    assert "Traceback" not in stderr
    written = frames(workdir / "cut")
    assert 3 <= len(written) < 1000
    for path in written:
        Image.open(path).load()   # raises on a truncated file
    video = list(iio.imiter(workdir / "cut.mp4", plugin="FFMPEG"))
    assert len(video) == len(written)
    assert f"kept the {len(written)} complete frames" in stderr and "cut.mp4" in stderr
    leftovers = [p.name for p in workdir.glob("cut*/*") if not p.name.startswith("frame_")]
    assert leftovers == [] and not list(workdir.glob("**/*softfem-part*"))


def test_the_camera_backs_off_when_a_body_would_leave_the_picture():
    from app.commands.export import SAFE_AREA, auto_framed, widened

    box = np.array([[-0.5, -0.5, -0.5], [0.5, 0.5, 0.5]])
    camera = auto_framed(box, 4 / 3, None)
    framed = (box[0], box[1])
    assert widened(camera, framed, box * 0.9, 4 / 3)[0] is camera     # still in view: it stays put
    grown = box * 3.0 + [1.0, 0.0, 0.0]                              # inflated and drifting
    wider, framed = widened(camera, framed, grown, 4 / 3)
    clip = np.c_[grown, np.ones(2)] @ wider.view_proj(4 / 3).T
    assert (np.abs(clip[:, :2] / clip[:, 3:]) <= SAFE_AREA).all()
    direction = lambda c: (c.eye - c.target) / np.linalg.norm(c.eye - c.target)  # noqa: E731
    np.testing.assert_allclose(direction(wider), direction(camera))  # the same view, from further
    assert widened(wider, framed, box, 4 / 3)[0] is wider            # and it never comes back closer


def test_the_writer_thread_raises_a_frames_error_and_begins_no_later_frame():
    """Frames are written on a thread: a full disk there stops the loop at its next frame, as
    when the loop wrote them itself."""
    from app.video import WriterThread
    from fem.errors import FemError

    for frames in (5, 3):     # frame 2 fails with frames to come, and as the last frame
        written = []

        def write(index):
            if index == 2:
                raise FemError("frame_00002.png: no space left on device")
            written.append(index)

        handed = []
        with pytest.raises(FemError, match="frame_00002.png: no space left on device"):
            with WriterThread(write) as thread:
                for index in range(frames):
                    thread.put(index)
                    handed.append(index)
        assert written == [0, 1] and handed == [0, 1, 2]


def test_a_failed_encoder_is_reported_with_its_cause(tmp_path):
    """The message names what the encoder said (a broken pipe, ffmpeg's status), or that its file
    is incomplete: a failure someone cannot reproduce can still be told apart."""
    import errno

    from app.video import VideoWriter

    writer = VideoWriter(tmp_path / "v.mp4", 25)
    broken = str(writer.failed(BrokenPipeError(errno.EPIPE, "Broken pipe")))
    assert broken == f"{tmp_path / 'v.mp4'}: the encoder failed (BrokenPipeError: [Errno 32] Broken pipe); " \
                     "the video was not written"
    said = str(writer.failed(OSError("FFMPEG returned error code 1\n\nFFMPEG COMMAND:\nffmpeg -y ...")))
    assert "(OSError: FFMPEG returned error code 1)" in said and "COMMAND" not in said
    assert "the encoder failed (its file is incomplete)" in str(writer.failed())
    assert "no space left on device" in str(writer.failed(OSError(errno.ENOSPC, "No space left on device")))
