"""tools/steady.py runs pytest with the arguments `make test` gives it: read from make itself, so that
a PYTEST_ARGS written with the Makefile's other variables comes out as make expands it."""

import shutil
from pathlib import Path

import pytest
from toolbox import load_tool

ROOT = Path(__file__).resolve().parents[2]


@pytest.mark.skipif(shutil.which("make") is None, reason="make is not installed (the README's commands need it)")
def test_the_arguments_are_make_tests_own(tmp_path):
    steady = load_tool("steady")
    args = steady.make_test_args(ROOT)
    assert args[args.index("-m") + 1] == "not long" and "-n" in args, args
    assert not any("$" in a for a in args), args                      # every variable expanded
    assert "-m" not in steady.without_marks(args) and "not long" not in steady.without_marks(args)
    # a Makefile of other words: its own PYTEST_ARGS, whatever variables it is written with
    (tmp_path / "Makefile").write_text('WORKERS := -n 3\nPYTEST_ARGS ?= $(WORKERS) -m "not slow" -x\n')
    assert steady.make_test_args(tmp_path) == ["-n", "3", "-m", "not slow", "-x"]
    (tmp_path / "Makefile").write_text("all:\n\ttrue\n")             # none: pytest's own defaults
    assert steady.make_test_args(tmp_path) == []
