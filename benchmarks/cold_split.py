"""Where a cold start goes: imports and the Mitsuba variant, ``load_model``, the first 256² frame (with a
cProfile of that frame's 25 largest cumulative entries).

    python benchmarks/cold_split.py MODEL [--size 256] [--env sky]

Run it in a fresh process (it is one); a second run finds the model's files in the page cache.
"""
import argparse
import cProfile
import os
import pstats
import sys
import time

t0 = time.perf_counter()
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("model")
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--env", default="sky")
    a = ap.parse_args()
    import speed
    import mifacerf as mf
    from mifacerf.variant import ensure_variant
    from mifacerf.evaluation.bench import process_age

    ensure_variant()
    t1 = time.perf_counter()
    face = mf.load_model(a.model)
    t2 = time.perf_counter()
    frame = speed.draw_frames(face, 1, 1)[0]
    prof = cProfile.Profile()
    prof.enable()
    speed.render(face, face.renderer, frame, a.size, a.env)
    prof.disable()
    t3 = time.perf_counter()
    print(f"imports + variant {t1 - t0:.2f} s, open {t2 - t1:.2f} s, first frame {t3 - t2:.2f} s, "
          f"process age {process_age():.2f} s")
    pstats.Stats(prof).sort_stats("cumulative").print_stats(25)


if __name__ == "__main__":
    main()
