"""The springblend panel in the 3D view's sidebar (N panel, springblend tab)."""

import bpy

from . import live, scene_data


class SPRINGBLEND_PT_main(bpy.types.Panel):
    """Server, character, colliders, live preview and bake."""
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
            box.operator("springblend.import_rig", icon="IMPORT")
        else:
            keys = obj.data.shape_keys
            count = len(scene_data.target_blocks(keys)) if keys else 0
            box.label(text=f"{obj.name}: {count} shape keys", icon="SHAPEKEY_DATA")
            character = obj.springblend_character
            box.label(text=f"Character {character[:12]}" if character else "Not uploaded",
                      icon="CHECKMARK" if character else "DOT")
            row = box.row(align=True)
            row.operator("springblend.upload", icon="EXPORT")
            row.operator("springblend.export_rig", text="", icon="FILE_TICK")
            row.operator("springblend.import_rig", text="", icon="IMPORT")
            box.operator("springblend.import_take", icon="ANIM")
            box.prop(obj, "springblend_hold_outer_rim")
            density = box.row(align=True)
            density.prop(obj, "springblend_path_intervals")
            density.prop(obj, "springblend_path_max_samples")

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

        box = layout.box()
        preview = live.active()
        box.operator("springblend.live_preview", text="Live Preview", icon="PLAY" if preview is None else "PAUSE",
                     depress=preview is not None)
        if preview is not None:
            box.label(text=f"{preview.object_name}: {preview.status()}", icon="LINKED")
        elif live.last_report():
            box.label(text=live.last_report(), icon="UNLINKED")

        box = layout.box()
        box.prop(settings, "bake_mode")
        if settings.bake_mode == "POINT_CACHE":
            box.prop(settings, "cache_directory")
        box.operator("springblend.bake", icon="RENDER_ANIMATION")


CLASSES = [SPRINGBLEND_PT_main]
