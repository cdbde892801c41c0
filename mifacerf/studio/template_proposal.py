"""A template proposed from the neutral's images alone (beyond the paper): placeholder."""
from __future__ import annotations


def propose_template(session) -> dict:
    return {"template": None, "note": "template proposal not implemented yet"}
