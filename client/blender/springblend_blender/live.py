"""Live preview: while it is on, every change of the character's shape-key values (dragging a slider, scrubbing
animated keys) or of a collider's placement is sent to an Interactive session on the server, and the newest
answer is shown on the mesh.

Threads. Blender's data is touched on the main thread only: the handlers (depsgraph update, frame change) read
the weights and collider motions and hand the newest request to a Channel; a timer (bpy.app.timers) takes the
newest answer and writes it into one shape key, "springblend_live", holding rest + (solved - linear blend of
the answer's weights), so the artist's keys still drive everything else and the mesh shows the solved shape.
The Channel's sender thread owns the gRPC calls (it looks up the character, opens the session, sends), its
reader thread waits for answers; neither calls bpy.

Answers the server marks as not converged are shown at once and replaced by a converged answer for the same
frame when one comes (the session asks for previews: the server answers each frame at once with the rig's
prediction, then with its solve; a frame that ends unconverged is shown too and its state says so). An answer older than the one shown is dropped.

Turning it off, loading another file, or a failure (the server gone, the character unknown) stops it and
leaves the mesh as it was: the live key is removed, the bake it hid shows again, and a report says why.
"""

import dataclasses
import threading
import time
import typing

import bpy
import numpy as np
from bpy.app.handlers import persistent

from . import connection, scene_data, store
from .scene_data import LIVE_KEY, UserError

POLL_SECONDS = 0.03
# Where the state a preview changes is kept on the object, so that a file saved while previewing is put back
# when it is opened again: the baked shape keys it muted and whether it hid the bake's Mesh Cache modifier.
RESTORE_PROPERTY = "springblend_live_restore"
# The server ended the session (idle for --idle-seconds) or its deadline passed: a new one opens on the next
# change, without a report.
_REOPEN_CODES = ("CANCELLED", "DEADLINE_EXCEEDED")


@dataclasses.dataclass
class Request:
    weights: tuple
    transforms: typing.Optional[tuple]  # one ((x, y, z), (w, x, y, z)) per collider, or None


@dataclasses.dataclass
class Answer:
    """A solved frame as the reader received it: serial (session, index) orders answers."""
    serial: tuple
    positions: np.ndarray
    converged: bool
    termination: str
    request: Request
    latency_ms: float  # from sending the request to receiving its answer
    sent: float        # time.monotonic() when the request was sent


class Channel:
    """The worker side of a preview: a sender and a reader thread around one Interactive session at a time.
    post() and take() are the main thread's only entry points; nothing here touches bpy."""

    def __init__(self, springblend, client_options, character_id, colliders):
        self._springblend = springblend
        self._client_options = dict(client_options)  # springblend.Client's arguments (connection.client_options)
        self._character_id, self._colliders = character_id, list(colliders)
        self._lock = threading.Condition()
        self._pending = None     # the newest request not yet sent
        self._session = None     # the open InteractiveSession
        self._generation = 0     # sessions opened so far
        self._sent = {}          # serial -> (request, time sent), until answered or overtaken
        self._answered = set()   # serials in _sent with an answer (an unconverged one may be followed)
        self._answer = None      # the newest answer not yet taken
        self._newest = None      # (serial, converged) of the newest answer kept so far
        self._error = None
        self._stopping = False
        self.target_names = None  # set once the character is known
        self.reopened = 0
        self._client = None
        self._sender = threading.Thread(target=self._send_loop, name="springblend-live-send", daemon=True)
        self._readers = []
        self._sender.start()

    # Main thread ----------------------------------------------------------------------------------------

    def post(self, request):
        """Makes request the next to send (an older unsent one is dropped)."""
        with self._lock:
            self._pending = request
            self._lock.notify_all()

    def take(self):
        """(newest answer not yet taken or None, error or None)."""
        with self._lock:
            answer, self._answer = self._answer, None
            return answer, self._error

    def solving(self):
        """True while a sent request has no answer yet."""
        with self._lock:
            return self._pending is not None or any(s not in self._answered for s in self._sent)

    def stop(self, wait=2.0):
        """Cancels the session and ends the threads (waits at most `wait` seconds; they are daemons)."""
        with self._lock:
            self._stopping = True
            session, self._session = self._session, None
            self._lock.notify_all()
        if session is not None:
            session.cancel()
        deadline = time.monotonic() + wait
        for thread in [self._sender] + self._readers:
            thread.join(max(0.0, deadline - time.monotonic()))
        if self._client is not None:
            self._client.close()

    def alive(self):
        """True while a thread of this channel still runs."""
        return any(t.is_alive() for t in [self._sender] + self._readers)

    # Worker threads -------------------------------------------------------------------------------------

    def deliver(self, serial, positions, summary, request=None, received=None):
        """Keeps a received answer when it is newer than every answer kept or shown so far, or is the converged
        answer of the frame whose unconverged preview is. The reader thread calls it for every SolvedFrame;
        request defaults to the one sent under serial. Returns whether the answer was kept."""
        received = time.monotonic() if received is None else received
        with self._lock:
            if request is None:
                if serial not in self._sent:
                    return False
                request, sent = self._sent[serial]
            else:
                sent = received
            # Requests of this session sent before this one were overtaken: the server never answers them.
            for older in [s for s in self._sent if s < serial]:
                del self._sent[older]
            self._answered.add(serial)
            self._answered.intersection_update(self._sent)
            newest = self._newest
            if newest is not None and (serial < newest[0] or (serial == newest[0] and (newest[1] or not summary.converged))):
                return False
            self._newest = (serial, bool(summary.converged))
            self._answer = Answer(serial=serial, positions=np.array(positions, dtype=np.float64),
                                  converged=bool(summary.converged), termination=summary.termination,
                                  request=request, latency_ms=(received - sent) * 1000.0, sent=sent)
            return True

    def _send_loop(self):
        try:
            self._client = self._springblend.Client(**self._client_options)
            names = list(self._client.get(self._character_id).target_names)
            with self._lock:
                self.target_names = names
        except Exception as error:  # noqa: BLE001 - handed to the main thread as a report
            self._fail(error)
            return
        while True:
            with self._lock:
                while self._pending is None and not self._stopping:
                    self._lock.wait()
                if self._stopping:
                    return
                request, self._pending = self._pending, None
                try:
                    # Opening a session and sending only queue work for gRPC's threads: neither blocks, so the
                    # lock that orders them against the reader's end-of-session handling is held briefly.
                    if self._session is None:
                        self._open_session()
                    index = self._session.send(list(request.weights), request.transforms and list(request.transforms))
                    self._sent[(self._generation, index)] = (request, time.monotonic())
                except Exception as error:  # noqa: BLE001
                    self._error = self._error or error
                    return

    def _open_session(self):
        self._session = self._client.interactive(self._character_id, colliders=self._colliders, previews=True)
        self._generation += 1
        reader = threading.Thread(target=self._read_loop, args=(self._session, self._generation),
                                  name="springblend-live-read", daemon=True)
        self._readers.append(reader)
        reader.start()

    def _read_loop(self, session, generation):
        try:
            for frame in session:
                self.deliver((generation, frame.index), frame.positions, frame.summary)
        except Exception as error:  # noqa: BLE001
            code = getattr(getattr(error, "code", None), "name", "")
            with self._lock:
                if self._stopping or generation != self._generation:
                    return
                if code in _REOPEN_CODES:
                    # Open a new session on the next change, resending the newest request left unanswered.
                    self._session = None
                    self.reopened += 1
                    unanswered = [s for s in self._sent if s[0] == generation]
                    if unanswered and self._pending is None:
                        self._pending = self._sent[max(unanswered)][0]
                    for serial in unanswered:
                        del self._sent[serial]
                    self._lock.notify_all()
                    return
            self._fail(error)

    def _fail(self, error):
        with self._lock:
            if not self._stopping and self._error is None:
                self._error = error


class Preview:
    """The main thread's side of the live preview of one object (at most one preview runs)."""

    def __init__(self, scene, obj, channel, address):
        self.scene_name, self.object_name, self.address = scene.name, obj.name, address
        self.channel = channel
        self.last_request = None
        self.shown = None        # the Answer on the mesh
        self.state = "connecting"
        self.message = ""
        self.applied_at = None   # time.monotonic() when self.shown went onto the mesh

    def status(self):
        """One line for the panel: connected, solving, converged or not, the last latency."""
        if self.state == "connecting":
            return "connecting..."
        parts = ["connected"]
        if self.channel.solving():
            parts.append("solving")
        if self.shown is not None:
            parts.append("converged" if self.shown.converged else f"not converged ({self.shown.termination})")
            parts.append(f"{self.shown.latency_ms:.0f} ms")
        return ", ".join(parts)


_preview = None   # the running Preview, or None
_last_report = ""  # what the last stop said (shown in the panel once the preview is off)


def active():
    """The running Preview, or None."""
    return _preview


def last_report():
    return _last_report


def start(context):
    """Starts the live preview of the active object; raises UserError when it cannot."""
    global _preview, _last_report
    if _preview is not None:
        stop("restarted")
    scene, obj = context.scene, context.active_object
    scene_data.shape_keys(obj)
    if not obj.springblend_character:
        raise UserError(f"'{obj.name}' has not been uploaded: press Upload Character first")
    springblend = connection.client_module()
    options = connection.client_options(scene)
    colliders = scene_data.collider_objects(scene.springblend.colliders)
    shapes = [scene_data.collider_message(springblend, scene_data.collider_geometry(obj, c)) for c in colliders]
    channel = Channel(springblend, options, obj.springblend_character, shapes)
    _hide_bake(obj)
    _preview = Preview(scene, obj, channel, options["address"])
    _last_report = ""
    if not bpy.app.timers.is_registered(poll):
        bpy.app.timers.register(poll, first_interval=POLL_SECONDS)


def stop(reason, level="INFO"):
    """Stops the preview and leaves the mesh as it was before it; reports why."""
    global _preview, _last_report
    preview, _preview = _preview, None
    if preview is None:
        return
    preview.channel.stop()
    obj = bpy.data.objects.get(preview.object_name)
    if obj is not None:
        restore(obj)
    _last_report = f"springblend live preview stopped: {reason}"
    report(level, _last_report)
    _redraw()


def update(scene=None):
    """Reads the character's current weights and collider motions and posts them when they changed. The
    depsgraph-update and frame-change handlers call it; so can a test."""
    preview = _preview
    if preview is None or (scene is not None and scene.name != preview.scene_name):
        return
    names = preview.channel.target_names
    if names is None:
        return  # poll() calls again once the character is known
    try:
        scene = bpy.data.scenes[preview.scene_name]
        obj = bpy.data.objects[preview.object_name]
        weights = tuple(scene_data.frame_weights(obj, names))
        colliders = scene_data.collider_objects(scene.springblend.colliders)
        transforms = tuple(scene_data.collider_motion(obj, c) for c in colliders) if colliders else None
    except (KeyError, ReferenceError):
        stop("the character or its scene is gone", "WARNING")
        return
    except UserError as error:
        stop(str(error), "ERROR")
        return
    request = Request(weights=weights, transforms=transforms)
    if request != preview.last_request:
        preview.last_request = request
        preview.channel.post(request)


def poll():
    """The timer on the main thread: puts the newest answer onto the mesh, stops on errors."""
    preview = _preview
    if preview is None:
        return None
    answer, error = preview.channel.take()
    if error is not None:
        stop(_describe(error, preview.address), "ERROR")
        return None
    if preview.state == "connecting" and preview.channel.target_names is not None:
        preview.state = "connected"
        update()
    if answer is not None:
        apply(preview, answer)
    _redraw()
    return POLL_SECONDS if _preview is preview else None


def apply(preview, answer):
    """Writes an answer into the live shape key: rest + (solved - linear blend of its weights)."""
    obj = bpy.data.objects.get(preview.object_name)
    if obj is None or obj.data.shape_keys is None:
        stop("the character is gone", "WARNING")
        return
    if obj.mode == "EDIT":
        return  # edit mode owns the mesh; the next answer after it shows
    keys = obj.data.shape_keys
    rest = scene_data.key_positions(keys.reference_key)
    if len(answer.positions) != len(rest):
        stop(f"'{obj.name}' has {len(rest)} vertices, the server's character {len(answer.positions)}: upload again",
             "ERROR")
        return
    # What Blender shows from the keys now (in-betweens, combinations and vertex-group masks included).
    linear = scene_data.shown_blend(obj, rest, scene_data.key_values(obj))
    live = keys.key_blocks.get(LIVE_KEY)
    if live is None:
        live = obj.shape_key_add(name=LIVE_KEY, from_mix=False)
        live.relative_key = keys.reference_key
    live.slider_min, live.slider_max, live.value, live.mute = 0.0, 1.0, 1.0, False
    corrected = rest + (answer.positions - linear)
    live.data.foreach_set("co", corrected.astype(np.float32).ravel())
    obj.data.update()
    preview.shown = answer
    preview.applied_at = time.monotonic()


def restore(obj):
    """Removes the live key and shows the bake the preview hid: the mesh as it was before the preview."""
    keys = obj.data.shape_keys if obj.type == "MESH" else None
    if keys is not None and keys.key_blocks.get(LIVE_KEY) is not None:
        obj.shape_key_remove(keys.key_blocks[LIVE_KEY])
    saved = obj.get(RESTORE_PROPERTY)
    if saved is not None:
        if keys is not None:
            for name in saved.get("muted", []):
                if name in keys.key_blocks:
                    keys.key_blocks[name].mute = False
        modifier = store.cache_modifier(obj)
        if modifier is not None and saved.get("cache_hidden"):
            modifier.show_viewport = True
        del obj[RESTORE_PROPERTY]
    if obj.type == "MESH":
        obj.data.update()


def _hide_bake(obj):
    """A bake would show on top of the preview: mute its keys and hide its modifier, noting what to undo."""
    keys = obj.data.shape_keys
    muted = [kb.name for kb in keys.key_blocks if kb.name.startswith(scene_data.BAKE_PREFIX) and not kb.mute]
    for name in muted:
        keys.key_blocks[name].mute = True
    modifier = store.cache_modifier(obj)
    cache_hidden = modifier is not None and modifier.show_viewport
    if cache_hidden:
        modifier.show_viewport = False
    obj[RESTORE_PROPERTY] = {"muted": muted, "cache_hidden": cache_hidden}


def _describe(error, address):
    if isinstance(error, UserError):
        return str(error)
    code = getattr(getattr(error, "code", None), "name", None)
    if code is not None:
        return f"springblend server {address}: {code}: {getattr(error, 'message', error)}"
    return f"{type(error).__name__}: {error}"


def report(level, message):
    """A Blender report from outside an operator (a timer or a handler), and a line on the console."""
    print(message)
    try:
        bpy.ops.springblend.live_report(level=level, message=message)
    except Exception:  # noqa: BLE001 - no window to report to (closing, background): the console has it
        pass


def _redraw():
    window_manager = bpy.context.window_manager
    for window in window_manager.windows if window_manager else ():
        for area in window.screen.areas:
            if area.type == "VIEW_3D":
                area.tag_redraw()


# Handlers: registered with the add-on, persistent across file loads, idle unless a preview runs.

@persistent
def on_depsgraph_update(scene, depsgraph=None):
    if _preview is not None:
        update(scene)


@persistent
def on_frame_change(scene, depsgraph=None):
    if _preview is not None:
        update(scene)


@persistent
def on_load_pre(*args):
    if _preview is not None:
        stop("the file was closed")


@persistent
def on_load_post(*args):
    """A file saved while previewing holds the live key: put the mesh back as it was."""
    for obj in bpy.data.objects:
        keys = obj.data.shape_keys if obj.type == "MESH" else None
        if RESTORE_PROPERTY in obj or (keys is not None and LIVE_KEY in keys.key_blocks):
            restore(obj)
            report("INFO", f"springblend: removed the live preview saved with '{obj.name}' (the mesh is as it was "
                           "before the preview)")


HANDLERS = [("depsgraph_update_post", on_depsgraph_update), ("frame_change_post", on_frame_change),
            ("load_pre", on_load_pre), ("load_post", on_load_post)]


def register():
    for name, handler in HANDLERS:
        getattr(bpy.app.handlers, name).append(handler)


def unregister():
    stop("the add-on was disabled")
    for name, handler in HANDLERS:
        handlers = getattr(bpy.app.handlers, name)
        if handler in handlers:
            handlers.remove(handler)
    if bpy.app.timers.is_registered(poll):
        bpy.app.timers.unregister(poll)
