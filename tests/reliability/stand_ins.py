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


# ------------------------------------------------------------------ the demo with stand-in stages
#: (step, output folder, its marker) of the stand-in demo, in the demo's order (capture: files only)
DEMO_FOLDERS = [("register", "capture/registration", "registration.json"), ("model", "model", "model.json"),
                ("renders", "renders", "index.json"), ("performance", "performance_render", "drive.json"),
                ("metrics", "bench", "bench.json")]
DEMO_STEPS = ["capture"] + [s for s, _, _ in DEMO_FOLDERS]


def run_demo(out: str, slow: float = 0.05, files: int = 4) -> None:
    """``mifacerf demo -o OUT --preset tiny`` with stand-in stages: capture writes ``capture/manifest.json``
    and ``capture/hand/h.json`` (the hand input: its text is the version every later stage writes) once;
    every later stage writes its output folder as a transaction (as the real stages do), ``files`` files
    ``slow`` seconds apart. Each stage logs ``start NAME`` / ``end NAME`` to ``OUT/../calls.log``."""
    from mifacerf import demo
    from mifacerf.formats.files import OutputFolder, atomic_write_bytes

    out = Path(out)
    calls = out.parent / "calls.log"

    def logged(name, fn):
        def stage(*a, **k):
            with open(calls, "a") as f:
                f.write(f"start {name}\n")
            result = fn()
            with open(calls, "a") as f:
                f.write(f"end {name}\n")
            return result
        return stage

    def capture():
        for rel, text in (("capture/manifest.json", "{}"), ("capture/hand/h.json", "a"), ("contact_sheet.png", "png")):
            if not (out / rel).exists():
                (out / rel).parent.mkdir(parents=True, exist_ok=True)
                atomic_write_bytes(out / rel, text.encode())
        return out / "capture"

    def folder(name, rel, marker, result=None, extra=None):
        def fn():
            version = (out / "capture" / "hand" / "h.json").read_text()
            with OutputFolder(out / rel, marker, what=name) as o:
                for i in range(files):
                    time.sleep(slow)
                    (o.root / f"f{i}.txt").write_text(f"{name} {version} {i}")
                (o.root / marker).write_text(json.dumps({"version": version}))
                o.finish()
            if extra:
                atomic_write_bytes(out / extra, f"{name} {version}".encode())
            return None if result is None else {**result, "version": version}
        return fn

    stages = {
        "stage_capture": logged("capture", capture),
        "stage_register": logged("register", folder("register", *DEMO_FOLDERS[0][1:])),
        "stage_model": logged("model", folder("model", *DEMO_FOLDERS[1][1:])),
        "stage_renders": logged("renders", folder("renders", *DEMO_FOLDERS[2][1:], {"frames": 27},
                                                  extra="renders.png")),
        "stage_performance": logged("performance", folder("performance", *DEMO_FOLDERS[3][1:], {"frames": 9})),
        "stage_metrics": logged("metrics", folder("metrics", *DEMO_FOLDERS[4][1:],
                                                  {"cases": {"summary": {}, "truth_noise_psnr": 40.0},
                                                   "bench": {"results": []}}, extra="metrics_cases.png")),
    }
    saved = {k: getattr(demo, k) for k in stages}
    try:
        for k, v in stages.items():
            setattr(demo, k, v)
        demo.demo_cmd.main(["-o", str(out), "--preset", "tiny"], standalone_mode=False)
    finally:
        for k, v in saved.items():
            setattr(demo, k, v)
