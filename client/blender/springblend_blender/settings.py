"""The add-on's settings: preferences, per-scene settings (server, colliders, frame range) and per-object
properties (the uploaded character's id, a collider's shape)."""

import bpy


class SpringblendPreferences(bpy.types.AddonPreferences):
    """Where to find the springblend Python client when it is not bundled in the add-on, and how to reach a
    secured farm: TLS and a token, as the CLI's --tls, --tls-ca, --tls-cert, --tls-key, --tls-server-name and
    --token. Preferences belong to the user, never to a .blend file, so a token does not travel with scenes."""
    bl_idname = __package__

    python_path: bpy.props.StringProperty(
        name="Client package",
        description="Directory holding the springblend Python package (e.g. build/release/python); not needed "
                    "when the add-on was installed from springblend_blender.zip",
        subtype="DIR_PATH")
    use_tls: bpy.props.BoolProperty(
        name="TLS", default=False,
        description="Use TLS, checking the server against the system's roots (on whenever a TLS file is set)")
    tls_ca: bpy.props.StringProperty(
        name="CA bundle", subtype="FILE_PATH",
        description="PEM CA bundle to check the server's certificate with (the CLI's --tls-ca)")
    tls_cert: bpy.props.StringProperty(
        name="Client certificate", subtype="FILE_PATH",
        description="PEM client certificate, for servers requiring mutual TLS (--tls-cert)")
    tls_key: bpy.props.StringProperty(
        name="Client key", subtype="FILE_PATH", description="PEM private key of the client certificate (--tls-key)")
    tls_server_name: bpy.props.StringProperty(
        name="Server name",
        description="Name the server's certificate must carry (default: the host of the server address; "
                    "--tls-server-name)")
    token: bpy.props.StringProperty(
        name="Token", subtype="PASSWORD",
        description="Sent on every call as 'authorization: Bearer TOKEN' (--token); empty: $SPRINGBLEND_TOKEN")

    def draw(self, context):
        layout = self.layout
        layout.prop(self, "python_path")
        box = layout.box()
        box.label(text="Secured farm")
        box.prop(self, "use_tls")
        for name in ("tls_ca", "tls_cert", "tls_key", "tls_server_name", "token"):
            box.prop(self, name)


class SpringblendSceneSettings(bpy.types.PropertyGroup):
    """Scene.springblend: the server and what a bake covers."""

    server: bpy.props.StringProperty(
        name="Server", default="",
        description="host:port of the springblend server or of the farm's load balancer (empty: "
                    "$SPRINGBLEND_SERVER, else 127.0.0.1:50051); TLS and the token are in the add-on's preferences")
    timeout: bpy.props.FloatProperty(
        name="Timeout", default=600.0, min=1.0, unit="TIME_ABSOLUTE",
        description="Seconds allowed for one call (a whole bake is one call)")
    colliders: bpy.props.PointerProperty(
        type=bpy.types.Collection, name="Colliders",
        description="Objects the mesh must not pass through: empties (sphere or cube display) and meshes; each "
                    "object's springblend shape (Object properties) says how it is sent")
    use_scene_range: bpy.props.BoolProperty(
        name="Scene range", default=True, description="Bake the scene's frame range")
    frame_start: bpy.props.IntProperty(name="Start", default=1, description="First frame to bake")
    frame_end: bpy.props.IntProperty(name="End", default=24, description="Last frame to bake")
    bake_mode: bpy.props.EnumProperty(
        name="Bake to", default="POINT_CACHE",
        items=[("POINT_CACHE", "Point Cache", "One PC2 file of every frame, played by a Mesh Cache modifier"),
               ("SHAPE_KEYS", "Shape Keys", "One corrective shape key per frame, keyed on its frame")],
        description="Where a bake goes; either kind replaces an earlier bake of both kinds")
    cache_directory: bpy.props.StringProperty(
        name="Cache Directory", default="//", subtype="DIR_PATH",
        description="Where point-cache bakes are written, as OBJECT.pc2 (// is the .blend's directory)")

    def frame_range(self, scene):
        """(first, last) frame of a bake."""
        if self.use_scene_range:
            return scene.frame_start, scene.frame_end
        return self.frame_start, self.frame_end


COLLIDER_SHAPES = [
    ("AUTO", "Auto", "Empty: sphere or cube display; mesh: a sphere when its vertices lie on one, else its box"),
    ("SPHERE", "Sphere", "The ball of the object's bounding box (largest half extent)"),
    ("BOX", "Box", "The object's bounding box"),
    ("MESH", "Mesh", "The object's (closed) triangle mesh"),
    ("NONE", "None", "Not a collider"),
]

CLASSES = [SpringblendPreferences, SpringblendSceneSettings]


def register_properties():
    bpy.types.Scene.springblend = bpy.props.PointerProperty(type=SpringblendSceneSettings)
    bpy.types.Object.springblend_character = bpy.props.StringProperty(
        name="Character", description="The springblend character id this mesh was uploaded as")
    bpy.types.Object.springblend_hold_outer_rim = bpy.props.BoolProperty(
        name="Hold Outer Rim", default=False,
        description="Hold the mesh's outer rim (a face mask's; its holes stay free) on the linear blend, as a mask "
                    "is stitched to its head: the character is then held whatever its shape keys move, so "
                    "colliders work. Vertices of a vertex group named 'springblend_fixed' are held too")
    bpy.types.Object.springblend_path_intervals = bpy.props.IntProperty(
        name="Path Steps", default=0, min=0, max=128,
        description="Target paths' continuation steps per unit of weight (0: the server's default, 16; else 4 to "
                    "128). A character whose paths snap often finishes more single-target frames locally from "
                    "denser paths, at more memory and a longer upload")
    bpy.types.Object.springblend_path_max_samples = bpy.props.IntProperty(
        name="Path Samples", default=0, min=0, max=256,
        description="Samples kept per target path (0: the server's default, 64; else 8 to 256)")
    bpy.types.Object.springblend_collider = bpy.props.EnumProperty(
        name="springblend shape", items=COLLIDER_SHAPES, default="AUTO",
        description="How this object is sent as a springblend collider")


def unregister_properties():
    del bpy.types.Object.springblend_collider
    del bpy.types.Object.springblend_path_max_samples
    del bpy.types.Object.springblend_path_intervals
    del bpy.types.Object.springblend_hold_outer_rim
    del bpy.types.Object.springblend_character
    del bpy.types.Scene.springblend
