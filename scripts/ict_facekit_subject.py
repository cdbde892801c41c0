"""Make a ``mifacerf synth --subject`` folder from the ICT FaceKit (github.com/ICT-VGL/ICT-FaceKit, MIT licence).

The FaceKit's ``FaceXModel/generic_neutral_mesh.obj`` (26,719 vertices, centimetres, +Y up, UDIM-style
UVs, 26,384 quads and triangles) names its sub-meshes only by material; its README lists 17 of them
by polygon range (face, head and neck, mouth socket, eye sockets, gums and tongue, teeth, eyeballs,
lacrimal fluid, eye blend, eye occlusion, eyelashes). This writes the neutral with one ``g`` group per
sub-mesh, links the 53 ARKit-named expression OBJs beside it and writes a ``subject.json``
(``scale`` 0.01). Nothing of the FaceKit is copied into this repository::

    python scripts/ict_facekit_subject.py ICT-FaceKit/FaceXModel OUT_FOLDER
"""
from __future__ import annotations

import json
import sys
from pathlib import Path

#: (name, first polygon, last polygon) from the FaceKit README's "Face Model Topology" table
SUBMESHES = (("Face", 0, 9229), ("Head and Neck", 9230, 11143), ("Mouth socket", 11144, 13225),
             ("Eye socket left", 13226, 13629), ("Eye socket right", 13630, 14033),
             ("Gums and tongue", 14034, 17005), ("Teeth", 17006, 21495), ("Eyeball left", 21496, 23093),
             ("Eyeball right", 23094, 24691), ("Lacrimal fluid left", 24692, 24854),
             ("Lacrimal fluid right", 24855, 25017), ("Eye blend left", 25018, 25032),
             ("Eye blend right", 25033, 25047), ("Eye occlusion left", 25048, 25175),
             ("Eye occlusion right", 25176, 25303), ("Eyelashes left", 25304, 25843),
             ("Eyelashes right", 25844, 26383))


def main(src: str, out: str) -> None:
    src_dir, out_dir = Path(src), Path(out)
    out_dir.mkdir(parents=True, exist_ok=True)
    starts = {a: name for name, a, _ in SUBMESHES}
    lines, k = [], 0
    for line in (src_dir / "generic_neutral_mesh.obj").read_text().splitlines():
        if line.startswith("f "):
            if k in starts:
                lines.append(f"g {starts[k]}")
            k += 1
        elif line.startswith(("usemtl", "mtllib")):
            continue
        lines.append(line)
    if k != SUBMESHES[-1][2] + 1:
        raise SystemExit(f"expected {SUBMESHES[-1][2] + 1} polygons, found {k}")
    (out_dir / "neutral.obj").write_text("\n".join(lines) + "\n")
    names = []
    for p in sorted(src_dir.glob("*.obj")):
        if p.name == "generic_neutral_mesh.obj" or p.stem.startswith("identity"):
            continue
        link = out_dir / p.name
        if not link.exists():
            link.symlink_to(p.resolve())
        names.append(p.stem)
    (out_dir / "subject.json").write_text(json.dumps({
        "neutral": "neutral.obj", "expressions": {n: f"{n}.obj" for n in names}, "scale": 0.01,
        "source": "ICT FaceKit (github.com/ICT-VGL/ICT-FaceKit), MIT licence"}, indent=1))
    print(f"{out_dir}: neutral.obj with {len(SUBMESHES)} groups, {len(names)} expressions")


if __name__ == "__main__":
    main(*sys.argv[1:3])
