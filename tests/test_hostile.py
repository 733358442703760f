"""Every hostile input of tests/hostile.py (the list docs/robustness.md shows): one `error:` line
and exit 2, or the run it asks for, never a traceback."""

import pytest

from hostile import HOSTILE, run_hostile


@pytest.mark.parametrize("case", HOSTILE, ids=[f"{case.kind}: {case.name}" for case in HOSTILE])
def test_hostile_input_gives_one_error_line_or_runs(case, tmp_path, monkeypatch):
    monkeypatch.setenv("FEM_CACHE_DIR", str(tmp_path / "cache"))
    code, stderr = run_hostile(case, tmp_path)
    assert code == case.exit, stderr
    assert "Traceback" not in stderr
    if case.exit == 2:
        lines = stderr.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("error: ") and len(lines[0]) < 600, stderr
