"""slscan for Blender: import a texture result (model, scanner views as cameras, view images).

Install this folder as an add-on (zip it, then Edit > Preferences > Add-ons > Install from
Disk); it adds File > Import > slscan result (texture.json). It needs nothing but Blender
(4.2 or later) and must not import slscan itself.
"""

bl_info = {
    "name": "slscan result importer",
    "author": "slscan authors",
    "version": (0, 1, 0),
    "blender": (4, 2, 0),
    "location": "File > Import > slscan result (texture.json)",
    "description": "Import an slscan texture result: textured model, scanner views as cameras "
    "with their images",
    "category": "Import-Export",
}

if "bpy" in locals():  # "Reload Scripts" in Blender: pick up edited modules
    import importlib

    importlib.reload(importer)  # noqa: F821
    importlib.reload(operators)  # noqa: F821

import bpy

from . import importer, operators  # noqa: F401 (importer: for the reload above)


def register() -> None:
    for cls in operators.CLASSES:
        bpy.utils.register_class(cls)
    bpy.types.TOPBAR_MT_file_import.append(operators.menu_func_import)


def unregister() -> None:
    bpy.types.TOPBAR_MT_file_import.remove(operators.menu_func_import)
    for cls in reversed(operators.CLASSES):
        bpy.utils.unregister_class(cls)
