"""The start-up measurements of the benchmark run and say what they measured (never timed here)."""

import fem
from app.bench import startup


def test_startup_measures_warm_second_and_beside():
    fem.init("cpu", "f32")
    numbers = startup.measure("cube86", repeats=1, cold=False)
    assert set(numbers) == {"warm_s", "taichi_s", "second_s", "beside_s"}
    assert all(value > 0 for value in numbers.values())


def test_the_windows_first_frames_are_left_out_without_a_display(monkeypatch):
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    monkeypatch.setattr(startup.shutil, "which", lambda tool: None)      # no Xvfb either
    assert startup.view_seconds("cube86") == {}
