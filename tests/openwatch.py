"""An audit hook that records every file opened under a folder: tests prove that a stage never reads the
synthetic ground truth (a real capture has none)."""
import sys
from pathlib import Path

_WATCH = {"root": None, "opened": []}


def _audit(event, args):
    root = _WATCH["root"]
    if root is not None and event == "open" and args and isinstance(args[0], (str, bytes)):
        path = args[0].decode() if isinstance(args[0], bytes) else args[0]
        if path.startswith(root):
            _WATCH["opened"].append(path)


sys.addaudithook(_audit)


class watch_opens:
    """Context manager: the list of files opened under ``root`` while inside it (kept after exit)."""

    def __init__(self, root):
        self.root = str(Path(root).resolve())

    def __enter__(self):
        _WATCH["opened"] = []
        _WATCH["root"] = self.root
        return _WATCH["opened"]

    def __exit__(self, *exc):
        _WATCH["root"] = None
