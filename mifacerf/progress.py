"""Progress bars, one meaning throughout mifacerf and capture.

**Convention**: a function's ``progress`` parameter is a bool — ``True`` shows the function's own tqdm
bar (on stderr), ``False`` shows none; status messages go to a separate ``log`` callable
(``log(message: str)``), never through ``progress``.
"""
from __future__ import annotations


def bar(iterable=None, progress: bool = True, **options):
    """``tqdm(iterable, disable=not progress, **options)``: the bar of a function that takes ``progress``
    (tqdm is imported on first use; ``options`` are tqdm's: ``desc``, ``unit``, ``total``, …)."""
    from tqdm.auto import tqdm

    return tqdm(iterable, disable=not progress, **options)
