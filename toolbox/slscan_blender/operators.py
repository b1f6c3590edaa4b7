"""Blender UI for the slscan importer: the import operator, its menu entry, the view panel."""

from __future__ import annotations

import bpy
from bpy.props import BoolProperty, FloatProperty, StringProperty
from bpy_extras.io_utils import ImportHelper

from .importer import ResultError, import_result, use_view


class IMPORT_SCENE_OT_slscan(bpy.types.Operator, ImportHelper):
    """Import an slscan texture result: the textured model and the scanner's views as cameras"""

    bl_idname = "import_scene.slscan"
    bl_label = "Import slscan Result"
    bl_options = {"REGISTER", "UNDO", "PRESET"}  # noqa: RUF012 (Blender wants a set)

    filename_ext = ".json"
    filter_glob: StringProperty(default="*.json", options={"HIDDEN"})

    import_model: BoolProperty(
        name="Import Model",
        default=True,
        description="Import the textured model (model.glb, through Blender's glTF importer)",
    )
    import_cameras: BoolProperty(
        name="Import Cameras",
        default=True,
        description="One camera per scanner view, with the view's exact intrinsics and pose, "
        "in the collection 'slscan views'",
    )
    camera_backgrounds: BoolProperty(
        name="View Images as Camera Backgrounds",
        default=True,
        description="Show each view's un-shaded image as its camera's background image",
    )
    background_alpha: FloatProperty(
        name="Background Opacity",
        default=0.5,
        min=0.0,
        max=1.0,
        description="Opacity of the view images drawn over the model in camera view",
    )
    set_scene_camera: BoolProperty(
        name="Look Through First View",
        default=True,
        description="Make the first view the scene camera, with its resolution and pixel aspect",
    )

    def draw(self, context):
        layout = self.layout
        layout.prop(self, "import_model")
        layout.prop(self, "import_cameras")
        col = layout.column()
        col.enabled = self.import_cameras
        col.prop(self, "camera_backgrounds")
        sub = col.column()
        sub.enabled = self.camera_backgrounds
        sub.prop(self, "background_alpha")
        col.prop(self, "set_scene_camera")

    def execute(self, context):
        try:
            out = import_result(
                context,
                self.filepath,
                import_model=self.import_model,
                import_cameras=self.import_cameras,
                camera_backgrounds=self.camera_backgrounds,
                background_alpha=self.background_alpha,
                set_scene_camera=self.set_scene_camera,
            )
        except ResultError as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        self.report(
            {"INFO"},
            f"slscan: imported {len(out['model'])} model object(s) and "
            f"{len(out['cameras'])} view camera(s)",
        )
        return {"FINISHED"}


class SLSCAN_OT_use_view(bpy.types.Operator):
    """Make this slscan view the scene camera, with the view's resolution and pixel aspect"""

    bl_idname = "slscan.use_view"
    bl_label = "Look Through This View"
    bl_options = {"REGISTER", "UNDO"}  # noqa: RUF012

    @classmethod
    def poll(cls, context):
        obj = context.object
        return obj is not None and obj.type == "CAMERA" and "slscan_width" in obj.data

    def execute(self, context):
        use_view(context.scene, context.object)
        return {"FINISHED"}


class DATA_PT_slscan_view(bpy.types.Panel):
    """Camera properties: the scanner view this camera reproduces."""

    bl_label = "slscan View"
    bl_space_type = "PROPERTIES"
    bl_region_type = "WINDOW"
    bl_context = "data"

    @classmethod
    def poll(cls, context):
        return SLSCAN_OT_use_view.poll(context)

    def draw(self, context):
        cam = context.object.data
        col = self.layout.column(align=True)
        col.label(text=f"View: {cam.get('slscan_view', '')}")
        col.label(text=f"Image: {cam['slscan_width']} x {cam['slscan_height']} px")
        col.label(text=f"fx, fy: {cam['slscan_fx']:.2f}, {cam['slscan_fy']:.2f} px")
        col.label(text=f"cx, cy: {cam['slscan_cx']:.2f}, {cam['slscan_cy']:.2f} px")
        self.layout.operator(SLSCAN_OT_use_view.bl_idname, icon="CAMERA_DATA")


def menu_func_import(self, context):
    self.layout.operator(IMPORT_SCENE_OT_slscan.bl_idname, text="slscan result (texture.json)")


CLASSES = (IMPORT_SCENE_OT_slscan, SLSCAN_OT_use_view, DATA_PT_slscan_view)
