"""The springblend panel in the 3D view's sidebar (N panel, springblend tab)."""

import bpy

from . import scene_data


class SPRINGBLEND_PT_main(bpy.types.Panel):
    """Server, character, colliders and bake."""
    bl_label = "springblend"
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "springblend"

    def draw(self, context):
        layout, settings = self.layout, context.scene.springblend
        row = layout.row(align=True)
        row.prop(settings, "server")
        row.operator("springblend.check_server", text="", icon="URL")

        obj = context.active_object
        box = layout.box()
        if obj is None or obj.type != "MESH":
            box.label(text="Select the character's mesh", icon="INFO")
        else:
            keys = obj.data.shape_keys
            count = len(scene_data.target_blocks(keys)) if keys else 0
            box.label(text=f"{obj.name}: {count} shape keys", icon="SHAPEKEY_DATA")
            character = obj.springblend_character
            box.label(text=f"Character {character[:12]}" if character else "Not uploaded",
                      icon="CHECKMARK" if character else "DOT")
            box.operator("springblend.upload", icon="EXPORT")

        layout.prop(settings, "colliders")
        if obj is not None and obj.type in {"EMPTY", "MESH"}:
            layout.prop(obj, "springblend_collider", text=f"{obj.name} as")
        col = layout.column(align=True)
        col.prop(settings, "use_scene_range")
        sub = col.row(align=True)
        sub.enabled = not settings.use_scene_range
        sub.prop(settings, "frame_start")
        sub.prop(settings, "frame_end")
        layout.prop(settings, "timeout")
        layout.operator("springblend.bake", icon="RENDER_ANIMATION")


CLASSES = [SPRINGBLEND_PT_main]
