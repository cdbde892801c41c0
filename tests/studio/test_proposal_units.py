"""Pieces of the proposals on their own: the two-view dots taken on the surface, one view without dots,
and the measurement script's matching and curve distance (scripts/studio_proposals.py)."""
import importlib.util
from pathlib import Path

import numpy as np


def test_ambiguous_two_view_dots_are_taken_where_they_continue_the_surface():
    """Dots 1 cm apart on a gently curved sheet; an ambiguous candidate on it is taken, its rival (the same
    peak paired with a neighbour's, centimetres off the sheet) is not, nor one too near a taken dot, nor one
    with too few neighbours."""
    from mifacerf.studio.template_proposal import _grow_on_surface

    g = np.arange(-3, 4) * 0.01
    xx, yy = np.meshgrid(g, g)
    Z = lambda x, y: 1.0 - 0.5 * (x ** 2 + y ** 2)        # noqa: E731 — a sheet of radius 1 m
    accepted = [np.array([x, y, Z(x, y)]) for x, y in zip(xx.ravel(), yy.ravel()) if abs(x - 0.0) > 1e-9 or y < 0]
    true = np.array([0.0, 0.005, Z(0.0, 0.005)])             # a dot between the taken ones, on the sheet
    rest = [({0: 1, 1: 7}, true),
            ({0: 1, 1: 8}, true + [0.0, 0.0, 0.025]),           # the same peak of view 0 with another of view 1
            ({0: 2, 1: 9}, accepted[0] + [0.001, 0.0, 0.0]),    # on a taken dot
            ({0: 3, 1: 10}, np.array([0.5, 0.5, 1.0]))]         # nothing near
    taken = [set(), set()]
    added = _grow_on_surface(accepted, rest, taken)
    assert len(added) == 1 and np.allclose(added[0], true)
    assert taken == [{1}, {7}]
    # a rival just as near the sheet: neither is taken (two views cannot tell them apart)
    rest[1] = ({0: 1, 1: 8}, true + [0.002, 0.0, 0.0005])
    assert _grow_on_surface(accepted, rest[:2], [set(), set()]) == []


def test_one_view_without_dots(capture, monkeypatch):
    """One camera's dot map blank (say, its dots washed out): an expression's proposals come from the
    other views, and the template's dot matching runs on them."""
    import mifacerf.studio.proposals as P
    from mifacerf.studio import template_proposal as TP
    from mifacerf.studio.session import Session

    s = Session(capture)
    real = P._strength_maps(s, "smile")
    one_blank = dict(real, cam2=np.zeros_like(real["cam2"]))
    monkeypatch.setattr(P, "_strength_maps", lambda session, name: dict(one_blank))
    r = P.propose_expression(s, "smile")
    assert r["state"] is not None and len(r["state"]["coarse"]) >= 8
    assert not any("cam2" in it["clicks"] for v, it in r["state"]["coarse"].items() if s.template().is_dot[int(v)])
    P3, summary = TP.detect_and_match(s.cams, one_blank)     # tiny has 3 views: two are left, no crash
    assert summary["peaks"][2] == 0 and summary["peaks"][0] > 30 and len(P3) == summary["points"]


def _script():
    path = Path(__file__).resolve().parents[2] / "scripts" / "studio_proposals.py"
    spec = importlib.util.spec_from_file_location("studio_proposals", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_the_measurement_matches_dots_one_to_one_and_measures_curves():
    from types import SimpleNamespace

    m = _script()
    truth = np.array([[0, 0, 0], [0.01, 0, 0], [0.02, 0, 0], [0.5, 0, 0]], float)
    tpl = SimpleNamespace(dot_ids=np.array([0, 1, 2, 3]),
                          vertices=np.array([[0.0004, 0, 0], [0.0006, 0, 0], [0.0201, 0, 0], [0.3, 0, 0]]))
    # both near truth 0: the nearer wins, the other is a phantom; one too far from anything
    assert m.match_truth(tpl, truth, np.arange(4)) == {0: 0, 2: 2}
    line = np.array([[0, 0], [10, 0]], float)
    assert m._curve_rms(np.array([[2, 1], [5, -1], [8, 1]], float), line) == 1.0
    assert abs(m._curve_rms(np.array([[13, 4]], float), line) - 5.0) < 1e-12       # past the end: to the end point


def test_the_lips_lower_edge_below_the_lower_lip():
    """The jaw flag's measure: the lowest lip pixel in each point's column, less the point's row (median)."""
    from mifacerf.studio.proposals import _lip_bottom_offset

    region = np.zeros((40, 40), bool)
    region[10:20, 5:30] = True                    # lips from row 10 to 19
    uv = np.array([[8.0, 15.0], [12.2, 14.0], [20.0, 16.0], [25.0, 15.0]])
    assert _lip_bottom_offset(region, uv) == 4.0      # 19 - 15 (the median of 4, 5, 3, 4)
    assert _lip_bottom_offset(region, uv + [20.0, 0.0]) is None      # no lip in those columns
