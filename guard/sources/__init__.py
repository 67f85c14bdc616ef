"""Sources: turn wire messages and log files into samples in SI units.

Log files are recognised by their content, not their name (`open_log`): each format's module gives
a `looks_like(head)` check of the file's first bytes and a reader class, registered in LOG_FORMATS
and imported only when a file of its kind is opened (as python-can's BACKENDS). Adding a format is
one module plus one line here. Live links: `guard.sources.link` (MAVLink UDP/TCP/serial) and
`guard.sources.can` (DroneCAN through python-can), chosen by `guard.sources.live.open_link`.
"""

from __future__ import annotations

import importlib
import os
from pathlib import Path

from guard.errors import SourceError
from guard.sources.base import LogSource

# format name -> (module, sniffing function, reader class)
LOG_FORMATS: dict[str, tuple[str, str, str]] = {
    "tlog": ("guard.sources.tlog", "looks_like_tlog", "TlogReader"),
    "dataflash": ("guard.sources.dataflash", "looks_like_dataflash", "DataFlashReader"),
    "ulog": ("guard.sources.ulog", "looks_like_ulog", "UlogReader"),
}
HEAD_BYTES = 64
LOG_SUFFIXES = (".tlog", ".bin", ".ulg")     # a file so named in a folder is taken as a log even if unreadable


def log_format(path: str) -> str | None:
    """The name of the format `path` holds, from its first bytes (None: none guard reads)."""
    try:
        with open(path, "rb") as f:
            head = f.read(HEAD_BYTES)
    except OSError as e:
        raise SourceError(f"{path}: cannot open: {e.strerror}") from None
    for name, (module, sniff, _) in LOG_FORMATS.items():
        if getattr(importlib.import_module(module), sniff)(head):
            return name
    return None


def open_log(path: str, **options) -> LogSource:
    """A reader for the log at `path`, whatever its format. `options` go to the reader
    (`system_id` for MAVLink logs, `imu` and `gnss` instance numbers where a log holds several)."""
    name = log_format(path)
    if name is None:
        if path.endswith(".tlog"):          # a tlog that starts with garbage: its reader resynchronises
            name = "tlog"
        else:
            known = ", ".join(LOG_FORMATS)
            raise SourceError(f"{path}: not a log guard reads (known formats: {known})")
    module, _, cls = LOG_FORMATS[name]
    return getattr(importlib.import_module(module), cls)(path, **options)


def find_logs(paths: list[str]) -> list[str]:
    """The logs at `paths`, each once (the first time it is named): a file as given; in a folder and
    its folders, in name order, each file whose content is a log guard reads or whose name says it is
    one (so that a log too damaged to be recognised is said, not passed over), and each folder that
    cannot be read (so that it is said too); other files (reports, plots, notes) are left. A
    SourceError names a path that is not there, or a folder without a log."""
    logs: list[str] = []
    for path in map(Path, paths):
        if path.is_dir():
            found = _logs_under(path)
            if not found:
                raise SourceError(f"{path}: no log in it or its folders (a .tlog, .bin or .ulg, by its content)")
            logs += found
        elif path.exists():
            logs.append(str(path))
        else:
            raise SourceError(f"{path}: no such file or folder")
    seen: set[Path] = set()
    return [p for p in logs if not (Path(p).resolve() in seen or seen.add(Path(p).resolve()))]


def _logs_under(folder: Path) -> list[str]:
    """The logs in `folder` and its folders, and the folders that could not be read, in name order."""
    found: list[str] = []
    unreadable: list[str] = []
    for root, _, files in os.walk(folder, onerror=lambda e: unreadable.append(e.filename)):
        found += [str(Path(root) / f) for f in files if _a_log(Path(root) / f)]
    return sorted(found + unreadable, key=lambda p: Path(p).parts)


def _a_log(path: Path) -> bool:
    """Named as a log, or holding one (a file that cannot be opened, and is not named as a log, is not)."""
    if path.suffix.lower() in LOG_SUFFIXES:
        return True
    try:
        return path.is_file() and log_format(str(path)) is not None
    except SourceError:
        return False
