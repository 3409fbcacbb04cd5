"""davis_rig.scene and davis_rig.scene.mocap export their modules' public API; importing them imports no torch."""

from __future__ import annotations

import importlib

import pytest

import davis_rig.scene as scene
import davis_rig.scene.mocap as mocap

SCENE_MODULES = ("aps", "background", "body", "camera", "contact", "gait", "gait_curves", "masks", "motion",
                 "quaternion", "skeleton", "rasterize", "renderer", "shading", "texture", "scene", "smpl")
MOCAP_MODULES = ("amass", "bvh", "retarget", "splits")
#: Functions named like their submodule: not re-exported (the submodule would shadow them once imported).
SHADOWED = {"rasterize", "retarget"}


@pytest.mark.parametrize("package, prefix, modules", [(scene, "davis_rig.scene", SCENE_MODULES),
                                                      (mocap, "davis_rig.scene.mocap", MOCAP_MODULES)])
def test_all_is_the_union_of_the_modules_public_names(package, prefix, modules):
    expected = set()
    for m in modules:
        mod = importlib.import_module(f"{prefix}.{m}")
        expected |= set(mod.__all__) - SHADOWED
        for name in set(mod.__all__) - SHADOWED:
            assert getattr(package, name) is getattr(mod, name), name
    assert sorted(package.__all__) == sorted(expected) and len(package.__all__) == len(expected)
    assert set(package.__all__) <= set(dir(package))


def test_submodules_stay_reachable_next_to_the_exports():
    import davis_rig.scene.rasterize

    assert scene.rasterize is davis_rig.scene.rasterize  # the module, as before
    assert scene.render_clip is importlib.import_module("davis_rig.scene.scene").render_clip


def test_import_does_not_import_torch(fresh_python):
    code = (
        "import sys\n"
        "import davis_rig.scene, davis_rig.scene.mocap\n"
        "assert 'torch' not in sys.modules, 'import davis_rig.scene imported torch'\n"
        "davis_rig.scene.generate_gait, davis_rig.scene.SceneSpec\n"
        "assert 'torch' not in sys.modules, 'a lazy name imported torch'\n"
        "print('ok')\n"
    )
    assert fresh_python(code) == "ok"
