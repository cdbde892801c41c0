"""When mifacerf's Mitsuba plugins (``facerf``, ``facerf_bsdf``) are registered, in fresh interpreters.

* a Mitsuba user (``import mitsuba``, ``set_variant``, then ``import mifacerf``) gets them at once and
  loads a scene file naming them with plain ``mi.load_file``;
* otherwise the first use of rendering (``mifacerf.load_model``) registers them, or
  ``mifacerf.register_plugins()`` on request; registering again changes nothing.
"""
import os
import subprocess
import sys

import pytest

from mifacerf.variant import find_libllvm, variant_name

SCENE = """<scene version="3.0.0">
    <integrator type="facerf"><string name="model" value="{model}"/></integrator>
    <shape type="sphere"><float name="radius" value="0.05"/>
        <bsdf type="facerf_bsdf"><string name="model" value="{model}"/></bsdf>
    </shape>
</scene>
"""

CHECK = """
scene = mi.load_file(XML)
assert type(scene.integrator()).__name__ == "FaceRFIntegrator", scene.integrator()
assert "mifacerf.plugins" in sys.modules
"""


@pytest.fixture(scope="module")
def scene_xml(toy_model, tmp_path_factory):
    path = tmp_path_factory.mktemp("plugin_scene") / "face.xml"
    path.write_text(SCENE.format(model=toy_model.root.resolve()))
    return path


def _run(code: str, xml) -> None:
    env = dict(os.environ)
    if variant_name().startswith("llvm") and "DRJIT_LIBLLVM_PATH" not in env:
        env["DRJIT_LIBLLVM_PATH"] = find_libllvm() or ""  # what ensure_variant does for a plain Mitsuba user
    head = f"import sys\nVARIANT = {variant_name()!r}\nXML = {str(xml)!r}\n"
    r = subprocess.run([sys.executable, "-c", head + code], capture_output=True, text=True, env=env, timeout=300)
    assert r.returncode == 0, r.stderr[-3000:]


def test_mitsuba_user_gets_the_plugins_from_import_mifacerf(scene_xml):
    _run("import mitsuba as mi\nmi.set_variant(VARIANT)\nimport mifacerf\n" + CHECK
         + "mifacerf.register_plugins()\nimport mifacerf.plugins\n" + CHECK, scene_xml)


def test_load_model_registers_the_plugins(scene_xml, toy_model):
    _run("import mifacerf\nassert 'mitsuba' not in sys.modules and 'mifacerf.plugins' not in sys.modules\n"
         f"mifacerf.load_model({str(toy_model.root)!r})\nimport mitsuba as mi\n" + CHECK, scene_xml)


def test_register_plugins_on_request_is_idempotent(scene_xml):
    _run("import mifacerf\nimport mitsuba as mi\nassert 'mifacerf.plugins' not in sys.modules\n"
         "mi.set_variant(VARIANT)\nassert mifacerf.register_plugins() is mi\nmifacerf.register_plugins()\n"
         + CHECK + "mifacerf.register_plugins()\n" + CHECK, scene_xml)
