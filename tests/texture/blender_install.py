"""Run inside Blender (bpy) by test_blender.py: install the add-on zip as a user would.

    python blender_install.py -- {extension,legacy} ZIP TEXTURE_JSON OUT_JSON

Point BLENDER_USER_RESOURCES at an empty folder first: the install goes there. Writes
OUT_JSON with the enabled add-on modules, whether the operator and menu entry exist, and
the objects an import through File > Import's operator made.
"""

from __future__ import annotations

import json
import sys

import bpy


def main(mode: str, zip_path: str, texture_json: str, out_json: str) -> None:
    bpy.ops.wm.read_factory_settings(use_empty=True)
    if mode == "extension":  # Edit > Preferences > Get Extensions > Install from Disk
        bpy.ops.extensions.package_install_files(
            filepath=zip_path, repo="user_default", enable_on_install=True
        )
    else:  # Edit > Preferences > Add-ons > Install (legacy add-on, reads bl_info)
        bpy.ops.preferences.addon_install(filepath=zip_path)
        bpy.ops.preferences.addon_enable(module="slscan_blender")
    out = {
        "addons": [a.module for a in bpy.context.preferences.addons],
        "operator": hasattr(bpy.types, "IMPORT_SCENE_OT_slscan"),
        "menu": [
            getattr(f, "__module__", "")
            for f in bpy.types.TOPBAR_MT_file_import._dyn_ui_initialize()
        ],
    }
    out["status"] = sorted(bpy.ops.import_scene.slscan(filepath=texture_json))
    out["objects"] = sorted((o.name, o.type) for o in bpy.context.scene.objects)
    with open(out_json, "w", encoding="utf-8") as f:
        json.dump(out, f)


if __name__ == "__main__":
    main(*sys.argv[sys.argv.index("--") + 1 :])
