"""The add-on's operators: check the server, upload the active mesh, bake a frame range. Every failure becomes
a Blender report (the server's message included), never a traceback. Upload and bake run modal from the UI:
their calls go on a worker thread (jobs.py) with a progress bar, the interface stays live, and Esc cancels."""

import contextlib
import os
import time

import bpy

from . import connection, jobs, live, rig_import, scene_data, store, take_import
from .scene_data import UserError


class _Guarded:
    """Runs an operator's work and turns any failure into an ERROR report and CANCELLED."""

    def execute(self, context):
        try:
            return self.run(context)
        except Exception as error:  # noqa: BLE001 - shown to the artist instead of a traceback
            return self.failed(context, error)

    def failed(self, context, error):
        if isinstance(error, UserError):
            self.report({"ERROR"}, f"springblend: {error}")
        elif isinstance(error, jobs.Cancelled):
            self.report({"WARNING"}, f"springblend: {self.bl_label.lower()} cancelled")
        elif isinstance(error, OSError):
            self.report({"ERROR"}, f"springblend: {error.filename or 'a file'}: {error.strerror or error}")
        else:
            springblend = _loaded_client()
            if springblend is not None and isinstance(error, springblend.SpringblendError):
                self.report({"ERROR"}, f"springblend server {connection.server_address(context.scene)}: "
                                       f"{error.code.name}: {error.message}")
            else:
                self.report({"ERROR"}, f"springblend: unexpected {type(error).__name__}: {error}")
        return {"CANCELLED"}


def _loaded_client():
    try:
        return connection.client_module()
    except UserError:
        return None


class SPRINGBLEND_OT_check_server(_Guarded, bpy.types.Operator):
    """Ask the springblend server's health service whether it is serving"""
    bl_idname = "springblend.check_server"
    bl_label = "Check Server"

    def run(self, context):
        springblend = connection.client_module()
        with connection.connect(context.scene) as client:
            try:
                status = client.health()
            except springblend.SpringblendError as error:
                raise UserError(f"no springblend server answers at {client.address}: {error.message}") from None
        if status != "SERVING":
            raise UserError(f"the springblend server at {client.address} is {status} (draining before it stops?)")
        self.report({"INFO"}, f"springblend server {client.address} is serving")
        return {"FINISHED"}


class SPRINGBLEND_OT_upload(jobs.ModalJob, _Guarded, bpy.types.Operator):
    """Upload the active mesh (its Basis) with its shape keys as the character's targets (the build runs on the
    server while Blender stays usable; Esc cancels it)"""
    bl_idname = "springblend.upload"
    bl_label = "Upload Character"
    bl_options = {"REGISTER", "UNDO"}

    @classmethod
    def poll(cls, context):
        return not jobs.RUNNING and context.active_object is not None and context.active_object.type == "MESH"

    def run(self, context):
        return self.run_job(context)

    def prepare(self, context):
        """The rig read on the main thread; the upload and its build followed on the worker."""
        obj = context.active_object
        rig = _character_rig(obj)
        client = connection.connect(context.scene)
        name = self._object_name = obj.name
        hold_outer_rim = bool(obj.springblend_hold_outer_rim)
        density = {"path_intervals": int(obj.springblend_path_intervals),
                   "path_max_samples": int(obj.springblend_path_max_samples)}
        self._counts = (len(rig.rest), len(rig.targets))

        def work(job):
            def progress(character_id, p):
                eta = f" of ~{p.estimate_ms / 1000:.0f} s" if p.estimate_ms else ""
                job.progress(p.targets_done / p.targets if p.targets else 0.0,
                             f"building '{name}' ({character_id[:12]}): {p.stage}, paths {p.targets_done}/"
                             f"{p.targets}, {p.elapsed_ms / 1000:.0f} s{eta}")

            job.progress(0.0, f"uploading '{name}'")
            with client:
                return client.upload_rig(rig, name=name, on_progress=progress, hold_outer_rim=hold_outer_rim,
                                         **density)

        return jobs.Job(work, "upload")

    def apply(self, context, items):
        pass

    def finish(self, context, job):
        character = job.result
        obj = bpy.data.objects.get(self._object_name)
        if obj is None:
            raise UserError(f"'{self._object_name}' was removed while it uploaded; its character is "
                            f"{character.id[:12]} on the server")
        obj.springblend_character = character.id
        how = "already on the server" if character.cache_hit else \
            f"rig built in {character.summary.precompute_ms:.0f} ms"
        self.report({"INFO"}, f"springblend: uploaded '{obj.name}' ({self._counts[0]} vertices, {self._counts[1]} "
                              f"targets) as {character.id[:12]}, {how}")
        return {"FINISHED"}


def _character_rig(obj):
    """The object's shape keys and vertex groups as a springblend.rigfile.Rig (README: Blender conventions)."""
    rigfile = connection.client_module().rigfile
    rest, faces, targets = scene_data.character_rig(obj)
    return rigfile.Rig(rest, faces, [rigfile.Target(**t) for t in targets],
                       fixed_vertices=scene_data.fixed_vertices(obj), path=f"'{obj.name}'")


class SPRINGBLEND_OT_export_rig(_Guarded, bpy.types.Operator):
    """Write the active mesh's shape keys and vertex groups as a springblend rig file (JSON, with OBJ meshes and
    mask files beside it), for springblend blend --rig and springblend upload --rig"""
    bl_idname = "springblend.export_rig"
    bl_label = "Export Rig File"

    filepath: bpy.props.StringProperty(subtype="FILE_PATH")
    filter_glob: bpy.props.StringProperty(default="*.json", options={"HIDDEN"})

    @classmethod
    def poll(cls, context):
        return context.active_object is not None and context.active_object.type == "MESH"

    def invoke(self, context, event):
        if not self.filepath:
            self.filepath = bpy.path.clean_name(context.active_object.name) + ".json"
        context.window_manager.fileselect_add(self)
        return {"RUNNING_MODAL"}

    def run(self, context):
        obj = context.active_object
        if not self.filepath:
            raise UserError("choose where to write the rig file")
        path = bpy.path.abspath(self.filepath)
        rig = _character_rig(obj)
        connection.client_module().rigfile.write_rig(path, rig)
        self.report({"INFO"}, f"springblend: wrote the rig of '{obj.name}' ({len(rig.targets)} targets) to {path}")
        return {"FINISHED"}


class SPRINGBLEND_OT_import_rig(_Guarded, bpy.types.Operator):
    """Import a rig file (a baked one from springblend bake-rig, or any) as a mesh with shape keys that play without
    the server: one slider per target, in-betweens and combination correctives driven by the sliders"""
    bl_idname = "springblend.import_rig"
    bl_label = "Import Rig File"
    bl_options = {"REGISTER", "UNDO"}

    filepath: bpy.props.StringProperty(subtype="FILE_PATH")
    filter_glob: bpy.props.StringProperty(default="*.json", options={"HIDDEN"})

    def invoke(self, context, event):
        context.window_manager.fileselect_add(self)
        return {"RUNNING_MODAL"}

    def run(self, context):
        if not self.filepath:
            raise UserError("choose the rig file to import")
        obj = rig_import.import_rig(context, bpy.path.abspath(self.filepath))
        for other in context.selected_objects:
            other.select_set(False)
        obj.select_set(True)
        context.view_layer.objects.active = obj
        keys = len(obj.data.shape_keys.key_blocks) - 1
        self.report({"INFO"}, f"springblend: imported '{obj.name}' ({len(obj.data.vertices)} vertices, {keys} shape "
                              "keys driven by its target sliders in Object Properties > Custom Properties)")
        return {"FINISHED"}


class SPRINGBLEND_OT_import_take(jobs.ModalJob, _Guarded, bpy.types.Operator):
    """Import a captured take (a Live Link Face CSV: ARKit's shapes per frame) onto the active character's sliders
    as keyframes at the take's frame rate, the scene's frame range set from it (read off the main thread; Esc
    cancels)"""
    bl_idname = "springblend.import_take"
    bl_label = "Import Take"
    bl_options = {"REGISTER", "UNDO"}

    filepath: bpy.props.StringProperty(subtype="FILE_PATH")
    filter_glob: bpy.props.StringProperty(default="*.csv", options={"HIDDEN"})
    map_path: bpy.props.StringProperty(
        name="Name Map", subtype="FILE_PATH",
        description="A JSON map of the take's shape names to sliders, for names the automatic matching misses "
                    "(docs/takes.md; the CLI's --map)")
    lost: bpy.props.EnumProperty(
        name="Lost Tracking", default="HOLD",
        items=[("HOLD", "Hold", "Rows where tracking was lost keep the last tracked weights (the take's timing)"),
               ("SKIP", "Skip", "Rows where tracking was lost are left out")],
        description="What rows where the capture lost the face become (the CLI's --lost)")
    start_frame: bpy.props.IntProperty(name="Start Frame", default=1, description="The frame of the take's first row")

    @classmethod
    def poll(cls, context):
        return not jobs.RUNNING and context.active_object is not None and context.active_object.type == "MESH"

    def invoke(self, context, event):
        if not self.filepath:
            context.window_manager.fileselect_add(self)
            return {"RUNNING_MODAL"}
        return jobs.ModalJob.invoke(self, context, event)

    def execute(self, context):
        if bpy.app.background or context.window is None:
            return _Guarded.execute(self, context)
        return jobs.ModalJob.invoke(self, context, None)  # chosen in the file browser: keyed off the main thread

    def run(self, context):
        return self.run_job(context)

    def prepare(self, context):
        obj = context.active_object
        if not self.filepath:
            raise UserError("choose the take (a Live Link Face CSV) to import")
        self._object_name, self._start = obj.name, int(self.start_frame)
        self._path = bpy.path.abspath(self.filepath)
        map_path = bpy.path.abspath(self.map_path) if self.map_path else None
        return take_import.prepare(obj, self._path, map_path, self.lost)

    def apply(self, context, items):
        obj = bpy.data.objects.get(self._object_name)
        if obj is None:
            raise UserError(f"'{self._object_name}' was removed while the take was imported")
        for name, kind, values in items:
            take_import.write_keys(obj, name, kind, values, self._start)

    def finish(self, context, job):
        performance = job.result
        take_import.set_timing(context.scene, performance, self._start)
        rate = f"{performance.frame_rate:g} fps" if performance.frame_rate else "the scene's frame rate (no timecode)"
        self.report({"INFO"}, f"springblend: keyed {len(performance.weights)} frames of {self._path} on "
                              f"'{self._object_name}' ({len(performance.target_names)} sliders) from frame "
                              f"{self._start}, {rate}")
        if performance.report.noteworthy:
            self.report({"WARNING"}, "springblend: take: " + "; ".join(performance.report.lines()[1:]))
        return {"FINISHED"}


class SPRINGBLEND_OT_bake(jobs.ModalJob, _Guarded, bpy.types.Operator):
    """Solve every frame of the range on the server and store the results: a PC2 point cache played by a Mesh
    Cache modifier, or one corrective shape key per frame (Blender stays usable while it solves; Esc cancels)"""
    bl_idname = "springblend.bake"
    bl_label = "Bake Frames"
    bl_options = {"REGISTER", "UNDO"}

    @classmethod
    def poll(cls, context):
        return not jobs.RUNNING and context.active_object is not None and context.active_object.type == "MESH"

    def run(self, context):
        return self.run_job(context)

    def prepare(self, context):
        """On the main thread: the frames' weights, colliders and motions read from the scene; the worker
        streams the solve (and writes the point cache); apply() stores corrective keys on the main thread."""
        scene, obj = context.scene, context.active_object
        if not obj.springblend_character:
            raise UserError(f"'{obj.name}' has not been uploaded: press Upload Character first")
        first, last = scene.springblend.frame_range(scene)
        if last < first:
            raise UserError(f"the frame range {first}..{last} is empty")
        scene_data.shape_keys(obj)
        if live.active() is not None:
            live.stop("a bake started")  # the bake replaces what the preview hid
        to_cache = scene.springblend.bake_mode == "POINT_CACHE"
        cache_path = _cache_path(scene, obj) if to_cache else None
        springblend = connection.client_module()
        client = connection.connect(scene)
        try:
            target_names = list(client.get(obj.springblend_character).target_names)
            if not to_cache:
                store.remove_bake(obj)
                store.remove_cache(obj)
            frames, request, shown_values = self._read_frames(scene, obj, target_names, first, last, springblend)
            rest = scene_data.key_positions(obj.data.shape_keys.reference_key)
            if len(rest) != len(obj.data.vertices):
                raise UserError(f"'{obj.name}' changed its vertex count since the upload: upload again")
        except BaseException:
            client.close()
            raise
        self._object_name = obj.name
        self._frames, self._shown_values, self._rest = frames, shown_values, rest
        self._range, self._to_cache, self._cache_path = (first, last), to_cache, cache_path
        self._colliders = len(request["colliders"])
        self._unconverged = []
        self._started = time.monotonic()
        character, name = obj.springblend_character, obj.name

        def work(job):
            with client:
                # A point cache is written beside its path and put in place only when every frame is in, so a
                # failed or cancelled bake leaves the earlier one playing.
                with (springblend.pointcache.PointCacheWriter(cache_path, len(rest), start_frame=first)
                      if to_cache else contextlib.nullcontext()) as cache:
                    for solved in client.solve_frames(character, **request):
                        if to_cache:
                            cache.add(solved.positions)
                        job.deliver((solved.index, None if to_cache else solved.positions,
                                     solved.summary.converged, solved.summary.termination))
                        job.progress((solved.index + 1) / len(frames),
                                     f"baking '{name}': frame {frames[solved.index]} "
                                     f"({solved.index + 1} of {len(frames)})")

        return jobs.Job(work, "bake")

    def apply(self, context, items):
        obj = bpy.data.objects.get(self._object_name)
        if obj is None:
            raise UserError(f"'{self._object_name}' was removed while it baked")
        for index, positions, converged, termination in items:
            frame = self._frames[index]
            if positions is not None:
                linear = scene_data.shown_blend(obj, self._rest, self._shown_values[index])
                store.store_frame(obj, frame, self._rest, linear, positions)
            if not converged:
                self._unconverged.append(f"{frame} ({termination})")

    def finish(self, context, job):
        obj = bpy.data.objects.get(self._object_name)
        if obj is None:
            raise UserError(f"'{self._object_name}' was removed while it baked")
        first, last = self._range
        if self._to_cache:
            store.remove_bake(obj)
            store.install_cache(obj, _modifier_path(context.scene, self._cache_path), first)
        seconds = time.monotonic() - self._started
        where = f" into {self._cache_path}" if self._to_cache else ""
        self.report({"INFO"}, f"springblend: baked frames {first}..{last} of '{obj.name}' ({len(self._frames)} "
                              f"frames, {self._colliders} colliders){where} in {seconds:.1f} s")
        if self._unconverged:
            self.report({"WARNING"}, f"springblend: frames not converged: {', '.join(self._unconverged)}")
        return {"FINISHED"}

    @staticmethod
    def _read_frames(scene, obj, target_names, first, last, springblend):
        """Steps the timeline over the range and collects each frame's weights, every key's value (what Blender
        shows, for the corrective keys) and the collider motions."""
        colliders = scene_data.collider_objects(scene.springblend.colliders)
        frames = list(range(first, last + 1))
        weights, values, motions, shapes = [], [], [], []
        current = scene.frame_current
        try:
            for frame in frames:
                scene.frame_set(frame)
                if frame == first:
                    shapes = [scene_data.collider_message(springblend, scene_data.collider_geometry(obj, c))
                              for c in colliders]
                weights.append(scene_data.frame_weights(obj, target_names))
                values.append(scene_data.key_values(obj))
                motions.append([scene_data.collider_motion(obj, c) for c in colliders])
        finally:
            scene.frame_set(current)
        request = {"weights": weights, "colliders": shapes, "collider_transforms": motions if colliders else None}
        return frames, request, values


def _cache_path(scene, obj):
    """The absolute path of the object's point cache, DIRECTORY/OBJECT.pc2, its directory created."""
    directory = scene.springblend.cache_directory.strip() or "//"
    if directory.startswith("//") and not bpy.data.filepath:
        raise UserError("save the .blend first (the point cache goes next to it), or set Cache Directory to an "
                        "absolute path")
    directory = bpy.path.abspath(directory)
    try:
        os.makedirs(directory, exist_ok=True)
    except OSError as error:
        raise UserError(f"cannot create the cache directory {directory}: {error.strerror}") from None
    return os.path.join(directory, bpy.path.clean_name(obj.name) + ".pc2")


def _modifier_path(scene, path):
    """The path the modifier reads: relative to the .blend (//...) when the setting is, so the file can move
    with its .blend."""
    if scene.springblend.cache_directory.strip().startswith("//") and bpy.data.filepath:
        return bpy.path.relpath(path)
    return path


class SPRINGBLEND_OT_live_preview(_Guarded, bpy.types.Operator):
    """Live preview on or off: while on, changing the shape-key values, the frame or a collider shows the
    physical shape, solved on the server"""
    bl_idname = "springblend.live_preview"
    bl_label = "Live Preview"

    @classmethod
    def poll(cls, context):
        if live.active() is not None:
            return True
        return context.active_object is not None and context.active_object.type == "MESH"

    def run(self, context):
        if live.active() is not None:
            live.stop("turned off")
            return {"FINISHED"}
        live.start(context)
        self.report({"INFO"}, f"springblend: live preview of '{context.active_object.name}' on "
                              f"{live.active().address}")
        return {"FINISHED"}


class SPRINGBLEND_OT_live_report(bpy.types.Operator):
    """Shows a message of the live preview (which runs outside any operator) as a Blender report"""
    bl_idname = "springblend.live_report"
    bl_label = "springblend Live Preview Report"
    bl_options = {"INTERNAL"}

    level: bpy.props.EnumProperty(items=[(v, v, "") for v in ("INFO", "WARNING", "ERROR")], default="INFO")
    message: bpy.props.StringProperty()

    def execute(self, context):
        self.report({self.level}, self.message)
        return {"FINISHED"}


CLASSES = [SPRINGBLEND_OT_check_server, SPRINGBLEND_OT_upload, SPRINGBLEND_OT_export_rig, SPRINGBLEND_OT_import_rig,
           SPRINGBLEND_OT_import_take, SPRINGBLEND_OT_bake, SPRINGBLEND_OT_live_preview,
           SPRINGBLEND_OT_live_report]
