"""While kernels compile, a start says so: app/compiling.py, fed by fem.runtime's compile listeners."""

import io

import taichi as ti

from app import compiling
from app.compiling import Compiling


def fresh_kernel():
    """A kernel Taichi has not compiled in this process (each call makes a new one)."""
    field = ti.field(float, 4)

    @ti.kernel
    def fill(value: float):
        for i in field:
            field[i] = value

    return fill, field


def test_each_kernel_compiled_is_counted_and_the_count_is_remembered_for_the_next_start(f32, tmp_path, monkeypatch):
    monkeypatch.setattr(compiling, "counts_path", lambda: str(tmp_path / "counts.json"))
    monkeypatch.setattr(compiling, "FIRST_LINE_S", 0.0)
    out = io.StringIO()
    with Compiling("box", "key", stream=out) as first:
        for _ in range(3):
            fill, field = fresh_kernel()
            fill(2.0)
        assert first.kernels == 3
    assert field.to_numpy().tolist() == [2.0] * 4
    lines = out.getvalue().splitlines()
    assert lines[0] == "box: compiling kernels, 1 (0 s)"
    assert lines[-1].startswith("box: compiled 3 kernels in ")

    out = io.StringIO()
    with Compiling("box", "key", stream=out):
        fresh_kernel()[0](1.0)
    assert out.getvalue().startswith("box: compiling kernels, 1 of 3 (0 s)")
    assert compiling.remembered_counts() == {"key": 1}


def test_nothing_is_said_when_nothing_compiles_or_when_it_is_quick(f32, tmp_path, monkeypatch):
    monkeypatch.setattr(compiling, "counts_path", lambda: str(tmp_path / "counts.json"))
    fill, _ = fresh_kernel()
    fill(0.0)
    out = io.StringIO()
    with Compiling("box", "key", stream=out):
        fill(1.0)                                      # compiled already
    with Compiling("box", "key", stream=out):
        fresh_kernel()[0](1.0)                        # under FIRST_LINE_S
    assert out.getvalue() == ""


def test_a_closed_stream_or_an_error_inside_loses_nothing(f32, tmp_path, monkeypatch):
    monkeypatch.setattr(compiling, "counts_path", lambda: str(tmp_path / "counts.json"))
    monkeypatch.setattr(compiling, "FIRST_LINE_S", 0.0)
    stream = io.StringIO()
    stream.close()
    try:
        with Compiling("box", "other", stream=stream):
            fresh_kernel()[0](1.0)
            raise KeyError("inside")
    except KeyError:
        pass
    assert compiling.remembered_counts() == {}                 # a start that failed is not a count
    from fem import runtime
    assert runtime.compile_listeners() == []


def test_start_done_ends_the_open_start_where_the_command_says(f32, tmp_path, monkeypatch):
    """export's first stepped frame ends its start: later kernels are not counted as the start's."""
    monkeypatch.setattr(compiling, "counts_path", lambda: str(tmp_path / "counts.json"))
    with Compiling("box", "key", stream=io.StringIO()) as start:
        fresh_kernel()[0](1.0)
        compiling.start_done()
        fresh_kernel()[0](1.0)
    assert start.kernels == 1 and compiling.remembered_counts() == {"key": 1}
