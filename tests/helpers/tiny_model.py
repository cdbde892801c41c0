"""A built model of the ``tiny`` preset: synthesise, register and build in one call (slow: minutes)."""
from pathlib import Path


def build_tiny_model(root, expressions) -> Path:
    """``root/synth`` (the tiny capture + truth, registered) and ``root/model`` built from it; returns root."""
    from mifacerf.registration import register_capture
    from mifacerf.rendering.build import build_model
    from mifacerf.synthetic.synth import synthesize

    root = Path(root)
    cap = synthesize(root / "synth", preset="tiny", expressions=list(expressions), progress=False)
    register_capture(cap, progress=False)
    build_model(cap, root / "model")
    return root
