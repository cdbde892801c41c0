"""Stand-ins for the reliability tests of the output folders (``mifacerf drive``, ``mifacerf track``) and of
the demo's steps: a face model that renders flat colours (no Mitsuba), a track folder of a few frames, and
the demo with tiny stages. Importable in a child process (``faults.py drive|demo ...``)."""
from __future__ import annotations

import json
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np

T, N_FRAMES, SIZE = 12, 6, 8


class FlatEnv:
    """An environment that is one colour in every direction."""

    def lookup(self, d):
        return np.full((len(d), 3), 0.2, np.float32)


class StandInFace:
    """What :func:`mifacerf.tracking.drive.drive` needs of a loaded model: frames of one flat colour that
    follows the frame number; ``slow`` seconds per frame; ``fail_at``: the frame whose render raises."""

    expressions = ["neutral", "smile"]

    def __init__(self, root, slow: float = 0.0, fail_at: int | None = None, shade: float = 0.5):
        self.model = SimpleNamespace(root=str(root), n_vertices=T, references={})
        self.slow, self.fail_at, self.shade = slow, fail_at, shade
        self.renderer = SimpleNamespace(render=self._render)

    def _render(self, V, W, cam, env, spp=4, seed=0, frame=0, parts=None):
        if frame == self.fail_at:
            raise RuntimeError(f"injected failure rendering frame {frame}")
        time.sleep(self.slow)
        img = np.zeros((cam.height, cam.width, 4), np.float32)
        img[2:6, 2:6] = (self.shade * (1 + frame / 10), 0.3, 0.2, 1.0)
        return img

    def target(self, mesh):
        w = np.zeros((T, 2))
        w[:, 0] = 0.5 + 0.05 * np.tanh(mesh[:, 0])
        w[:, 1] = 1 - w[:, 0]
        return None, w

    def camera(self, camera=None, size=None):
        from mifacerf.camera import Camera

        K = np.array([[10.0, 0, SIZE / 2], [0, 10.0, SIZE / 2], [0, 0, 1]])
        return Camera("cam0", SIZE, SIZE, K, np.zeros(5), np.eye(3), np.array([0, 0, 1.0]))

    def environment(self, name):
        return FlatEnv()


def make_track(root: Path, seed: int = 0) -> Path:
    """A track folder of :data:`N_FRAMES` frames of :data:`T` vertices (what :class:`Track` reads)."""
    from mifacerf.formats.files import save_npz_atomic, write_json_atomic
    from mifacerf.tracking.track import FORMAT, VERSION

    root.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    save_npz_atomic(root / "track.npz", vertices=rng.normal(size=(N_FRAMES, T, 3)) * 0.01,
                    eyes=np.tile(np.eye(4), (N_FRAMES, 2, 1, 1)), head_pose=np.tile(np.eye(4), (N_FRAMES, 1, 1)))
    write_json_atomic(root / "track.json", {"format": FORMAT, "version": VERSION, "n_frames": N_FRAMES,
                                            "fps": 30.0, "cameras": ["cam0"]})
    return root


def run_drive(track: str, out: str, slow: float = 0.0, fail_at=None, shade: float = 0.5) -> str:
    """``drive`` of the stand-in face (no video), as the tests and a killed child run it."""
    from mifacerf.tracking.drive import drive

    face = StandInFace(Path(track).parent / "model", slow=slow, fail_at=fail_at, shade=shade)
    return str(drive(track, face, out, envs=("flat",), video=False, progress=False))


def drive_state(out: Path) -> dict:
    """What a complete drive folder holds, checked: drive.json names every frame written."""
    meta = json.loads((out / "drive.json").read_text())
    frames = sorted(p.name for p in (out / "flat" / "frames").glob("F*"))
    first, stop = meta["frames"]
    assert frames == sorted(f"F{f:05d}.{e}" for f in range(first, stop) for e in ("exr", "png")), frames
    assert (out / "weights.npz").exists() and "flat" in meta["environments"]
    return meta
