"""A script of tools/ loaded in the tests: tools/ is a folder of scripts, not a package guard installs.

    from toolbox import load_tool
    faults = load_tool("faults")                       # tools/faults.py
    harness = load_tool("eval", as_name="guard_eval")  # registered under that name

Each is loaded once and registered in sys.modules (under `as_name`, else its file's stem), so that
the worker processes a tool starts find its functions by that name.
"""

import importlib.util
import sys
from pathlib import Path

TOOLS = Path(__file__).resolve().parents[1] / "tools"


def load_tool(stem: str, as_name: str | None = None):
    name = as_name or stem
    if name in sys.modules:
        return sys.modules[name]
    spec = importlib.util.spec_from_file_location(name, TOOLS / f"{stem}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module
