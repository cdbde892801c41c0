"""The extensions' outline fit from the neutral alone against a joint fit over the neutral and other poses
(``refine_to_silhouettes(poses=...)``), both against the Phong surface (level 3), on a ``mifacerf synth``
folder whose capture is registered (evaluation only: it reads the synthetic truth)::

    python scripts/outline_poses.py SYNTH_OUT head_turn_left,head_turn_right,head_up,head_down

Prints, for the user's template and each fit placed in six expressions, the extension vertices' offset from
the truth's template vertices along the truth's normals (mm; rigid / driven extensions), then the outline
error in 30 novel views (yaw -30..30, pitch -8 / 6; 128², neutral, fear, smile): the summed |Δα| of the
Phong surface's coverage (16 spp) against the truth's alpha (16 spp), and its signed sum (+: outside)."""
import json, sys, time, numpy as np
from mifacerf.synthetic.truth_scene import TruthRenderer
from mifacerf.formats.capture import Capture
from mifacerf.formats.registration import Registration
from mifacerf.registration.extensions import (extensions_from_template, place_in_expression, silhouette_matte,
                                              refine_to_silhouettes)
from mifacerf.registration.proxies import proxies_for
from mifacerf.registration.texcoords import texture_coordinates
from mifacerf.geometry.visibility import Visibility, vertex_normals
from mifacerf.geometry.footprint import centre_footprint
synth = sys.argv[1]
extra = sys.argv[2].split(",")
tr = TruthRenderer.from_synth(synth)
cap = Capture(f"{synth}/capture")
reg = Registration(f"{synth}/capture/registration")
hand = json.load(open(f"{synth}/capture/hand/template.json"))
X = np.array([v["position"] for v in hand["vertices"]])
F = np.array(reg.template["triangles"])
exts = extensions_from_template(hand, len(X))
ext = np.zeros(len(X), bool)
for e in exts: ext[e.vertices] = True
ids = np.flatnonzero(ext)
dots = np.array([i for i, v in enumerate(hand["vertices"]) if v["kind"] == "dot"])
cams = list(cap.rig.cameras)
vis = Visibility(F, len(X), tol=max(0.5 * centre_footprint(cams), 5e-4))

def placed(Xt, name, N0=None):
    r = reg.expression(name)
    V = r.vertices.copy(); st = r.status.copy()
    place_in_expression(Xt, F, dots, exts, V, st, r.head_pose, neutral=N0)
    return V, r.head_pose

rn = reg.expression("neutral")
def view(name, Xt):
    V, H = placed(Xt, name, rn if name != "neutral" else None)
    mattes = [silhouette_matte(proxies_for(cap, name, c.name).diffuse) for c in cams]
    _, visible = texture_coordinates(V, cams, vis)
    return V, H, mattes, visible

rigid = np.zeros(len(X), bool)
for e in exts:
    if e.mode == "rigid": rigid[e.vertices] = True
def err(Xt, names, show=False):
    out = []
    for n in names:
        V, _ = placed(Xt, n, rn if n != "neutral" else None)
        truth = tr.subject.pose(tr.expressions[n], textures=False).template_vertices[:len(X)]
        N = vertex_normals(truth, F)
        o = ((V - truth) * N).sum(1)[ext] * 1000
        out.append((np.abs(o).mean(), o.mean(), np.percentile(np.abs(o), 95)))
        if show:
            oo = ((V - truth) * N).sum(1) * 1000
            print(f"    {n:16s} rigid |.| {np.abs(oo[rigid]).mean():.2f} mean {oo[rigid].mean():+.2f}; driven |.| {np.abs(oo[ext & ~rigid]).mean():.2f} mean {oo[ext & ~rigid].mean():+.2f}")
    return np.array(out).mean(0)

names = ["neutral", "fear", "smile", "head_turn_left", "head_up", "mouth_open_wide"]
print("user's template        |.| %.2f mean %+.2f p95 %.2f mm" % tuple(err(X, names, True)))
V0, H0, m0, vis0 = view("neutral", X)
fitted = {}
for label, poses in (("neutral only", []), ("neutral + " + ",".join(extra), extra)):
    t = time.time()
    P = [view(n, X) for n in poses]
    for v, _, m, vi in P:
        vi[:, ~rigid] = False      # other poses: the rigid extensions only
    moved, rep = refine_to_silhouettes(V0, F, ids, cams, m0, vis0, curved=3,
                                       poses=[(v, cams, m, vi) for v, _, m, vi in P])
    Xt = X.copy()
    Xt[ids] += (moved[ids] - V0[ids]) @ H0[:3, :3]
    print(f"{label:22s} |.| %.2f mean %+.2f p95 %.2f mm" % tuple(err(Xt, names, True)),
          f"({time.time()-t:.1f} s, offsets {rep['rounds'][0]['mean_abs_offset_mm']:.2f} -> {rep['rounds'][-1]['mean_abs_offset_mm']:.2f}, measured {rep['rounds'][0]['measured']})")
    fitted[label] = Xt

# --- the outline in novel views: Phong surface (level 3) coverage against the truth's alpha
from mifacerf.geometry.meshscene import CurvedMeshScene
from mifacerf.registration.extensions import mesh_matte
fits = {"user": X, **fitted}
views = [(y, p) for y in (-30, -19, 0, 19, 30) for p in (-8, 6)]
res = {k: [] for k in fits}
for n in ["neutral", "fear", "smile"]:
    for y, p in views:
        cam = tr.camera(yaw=y, pitch=p).resized(128, 128)
        a = tr.render(tr.expressions[n], cam, "sky", spp=16, seed=1)[..., 3]
        for k, Xt in fits.items():
            V, _ = placed(Xt, n, rn if n != "neutral" else None)
            m = mesh_matte(CurvedMeshScene(V, F, 3), cam, spp=16)
            res[k].append((np.abs(m - a).sum(), (m - a).sum()))
for k, v in res.items():
    v = np.array(v)
    print(f"novel views: {k[:24]:24s} |d alpha| sum {v[:,0].mean():.1f} px, signed {v[:,1].mean():+.1f} px (mean of {len(v)})")
