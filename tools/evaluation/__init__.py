"""The evaluation harness's parts: its cases, its runs (in worker processes), its summary and
figures. `tools/eval.py` is the command."""
