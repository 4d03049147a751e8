"""The Python client of a springblend server: what a DCC plug-in (Blender, Maya, Houdini) calls.

Every call raises SpringblendError carrying the server's status code and message. Arrays go in and come out
as numpy arrays in the rest mesh's vertex order.
"""

import dataclasses
import os
import queue
import threading
import typing

import grpc
import numpy as np

from springblend import arrays, colliders as shapes, performance, pointcache, rigfile, routing
from springblend._generated import health_pb2, pb, pb_grpc
from springblend.errors import SpringblendError, bad_answer, invalid_argument

# The metadata header that names the character of a call, so a load balancer can route by it (the C++
# client's kCharacterHeader).
CHARACTER_HEADER = "x-springblend-character"
# The initial metadata of an upload that names its character once the pieces are checked (the C++ client's
# kCharacterIdMetadata): the build can be followed with GetCharacter(no_wait) from then on.
CHARACTER_ID_METADATA = "springblend-character-id"
# Seconds between two looks at a build's progress (the C++ client's and the CLI's).
PROGRESS_INTERVAL = 0.5

# The environment variables the CLI reads too: the server's address when none is given, and the token.
SERVER_VARIABLE = "SPRINGBLEND_SERVER"
TOKEN_VARIABLE = "SPRINGBLEND_TOKEN"
DEFAULT_SERVER = "127.0.0.1:50051"


@dataclasses.dataclass
class SolvedFrame:
    """One solved frame: index in the request (or in the session), #V by 3 float32 positions, optional normals,
    and the server's FrameSummary (converged, termination, newton_iterations, residual, contacts, served_by ...).
    """
    index: int
    positions: np.ndarray
    normals: typing.Optional[np.ndarray]
    summary: typing.Any


@dataclasses.dataclass
class Solution:
    """A whole Solve: positions is #frames by #V by 3 float32; summaries one FrameSummary per frame."""
    positions: np.ndarray
    normals: typing.Optional[np.ndarray]
    summaries: list

    @property
    def converged(self):
        """True when every frame's Newton solve converged."""
        return all(s.converged for s in self.summaries)

    def write_pc2(self, path, start_frame=1.0, sample_rate=1.0):
        """Writes the frames as a PC2 point cache (springblend.pointcache): frame i is sample i, played at
        start_frame + i * sample_rate (by default frame = index + 1, as the CLI writes)."""
        pointcache.write_pc2(path, self.positions, start_frame, sample_rate)


class Client:
    """A connection to one server (or a load balancer in front of a farm).

    The TLS and token arguments are the CLI's --tls, --tls-ca, --tls-cert, --tls-key, --tls-server-name and
    --token, with the same environment variables.

    Args:
        address: host:port of the server; None: $SPRINGBLEND_SERVER, else 127.0.0.1:50051.
        timeout: seconds allowed for each call (a Solve stream counts as one call); None: no limit.
        piece_bytes: upload piece size, well under gRPC's 4 MiB message limit.
        tls: use TLS, checking the server against the system's roots (implied by tls_ca, tls_cert, tls_key).
        tls_ca: a PEM CA bundle to check the server's certificate with.
        tls_cert, tls_key: this client's PEM certificate and key, for servers that require mutual TLS.
        tls_server_name: the name the server's certificate must carry (default: the host of address).
        token: sent on every call as "authorization: Bearer TOKEN"; None: $SPRINGBLEND_TOKEN; "": none.
    """

    def __init__(self, address=None, timeout=600.0, piece_bytes=1 << 20, *, tls=False, tls_ca=None, tls_cert=None,
                 tls_key=None, tls_server_name=None, token=None):
        self.address, self.address_source = _resolve_address(address)
        self.timeout = timeout
        self.piece_bytes = piece_bytes
        self.tls = bool(tls or tls_ca or tls_cert or tls_key)
        self._token = os.environ.get(TOKEN_VARIABLE, "") if token is None else token
        options = [("grpc.max_receive_message_length", 256 << 20)]
        if self.tls:
            if bool(tls_cert) != bool(tls_key):
                raise invalid_argument("tls_cert and tls_key go together (the client certificate and its key)")
            credentials = grpc.ssl_channel_credentials(root_certificates=_read_pem("tls_ca", tls_ca),
                                                       private_key=_read_pem("tls_key", tls_key),
                                                       certificate_chain=_read_pem("tls_cert", tls_cert))
            if tls_server_name:
                options.append(("grpc.ssl_target_name_override", tls_server_name))
            self._channel = grpc.secure_channel(self.address, credentials, options=options)
        else:
            self._channel = grpc.insecure_channel(self.address, options=options)
        self._characters = pb_grpc.CharacterServiceStub(self._channel)
        self._target_names = {}  # character id -> its weight names (target_names)
        self._solves = pb_grpc.SolveServiceStub(self._channel)
        self._health = self._channel.unary_unary(
            "/grpc.health.v1.Health/Check",
            request_serializer=health_pb2.HealthCheckRequest.SerializeToString,
            response_deserializer=health_pb2.HealthCheckResponse.FromString)

    def close(self):
        """Closes the channel; the client cannot be used afterwards."""
        self._channel.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    # ---------------------------------------------------------------------------------------------------
    # Characters

    def upload(self, rest, faces, targets, target_names=None, name="", fixed_vertices=(), static_tolerance=0.0,
               no_interior=False, no_anchor=False, bending_stiffness=0.0, no_target_paths=False, hold_outer_rim=False,
               path_intervals=0, path_max_samples=0, on_progress=None):
        """Uploads a character and returns its Character message (id, cache_hit, summary, target_names).

        Args:
            rest: #V by 3 rest positions.
            faces: #F by 3 triangles, 0-based indices into rest; every target shares them.
            targets: a dict name -> #V by 3 positions (in weight order), or a list of arrays with target_names.
            target_names: one unique name per target when targets is a list.
            name: a label for people (not part of the id).
            fixed_vertices, static_tolerance, no_interior, no_anchor, bending_stiffness, no_target_paths,
                hold_outer_rim, path_intervals, path_max_samples: the rig builder's BuildOptions (zero values
                mean the server's defaults). hold_outer_rim holds an open surface's outer rim (a face mask's) on
                the linear blend, so a rig whose targets move every vertex is held and takes colliders and pins.
                path_intervals (steps per unit of weight, [4, 128], default 16) and path_max_samples (per
                target, [8, 256], default 64) make the target paths denser: more single-target frames finish
                locally where a character's paths snap often, at more memory and upload time.
            on_progress: None, or a function called as on_progress(character_id, progress) about twice a second
                while the server builds the character, progress being a BuildProgress message (stage, targets,
                targets_done, path_samples, elapsed_ms, estimate_ms, from_cache_file). It runs on the calling
                thread; an exception it raises cancels the upload (the server then stops the build) and goes
                up to the caller. A build takes from a second (the cylinder) to minutes (a face).
        """
        if isinstance(targets, dict):
            target_names, targets = list(targets.keys()), list(targets.values())
        targets = list(targets)
        if target_names is None or len(target_names) != len(targets):
            raise invalid_argument(f"upload: {len(targets)} targets need as many target_names, got "
                                   f"{None if target_names is None else len(target_names)}")
        rest = arrays.as_points(rest, "rest")
        faces = arrays.as_faces(faces, len(rest))
        shapes_ = [rest]
        for target_name, target in zip(target_names, targets):
            points = arrays.as_points(target, f"target '{target_name}'")
            if points.shape != rest.shape:
                raise invalid_argument(f"target '{target_name}': {len(points)} vertices, but the rest mesh has "
                                       f"{len(rest)}")
            shapes_.append(points)
        options = pb.BuildOptions(fixed_vertices=[int(v) for v in fixed_vertices],
                                  static_tolerance=float(static_tolerance), no_interior=bool(no_interior),
                                  no_anchor=bool(no_anchor), bending_stiffness=float(bending_stiffness),
                                  no_target_paths=bool(no_target_paths), hold_outer_rim=bool(hold_outer_rim),
                                  path_intervals=int(path_intervals), path_max_samples=int(path_max_samples))
        header = pb.UploadHeader(name=name, vertex_count=len(rest), face_count=len(faces),
                                 target_names=[str(n) for n in target_names], options=options)
        return self._upload(header, faces, shapes_, {}, on_progress)

    def upload_rig(self, rig, name="", fixed_vertices=(), on_progress=None, **options):
        """Uploads a production rig (springblend.rigfile.Rig, or the path of a rig file): targets with
        in-betweens, masks and combinations. Solves then take one weight per target that is not a combination
        (rig.weight_names). The server's refusals ("target 'jawOpen': inbetweens[1].weight ...") get the rig
        file's path in front. options: static_tolerance, no_interior, no_anchor, bending_stiffness,
        no_target_paths, hold_outer_rim, path_intervals, path_max_samples, and on_progress, as for upload."""
        if isinstance(rig, (str, bytes)) or hasattr(rig, "__fspath__"):
            rig = rigfile.load_rig(rig)
        rest = arrays.as_points(rig.rest, "rest")
        faces = arrays.as_faces(rig.faces, len(rest))
        shapes_, inbetweens, masks, specs = [rest], [], {}, []
        for index, target in enumerate(rig.targets):
            where = f"{rig.path}: target '{target.name}'"
            shapes_.append(self._same_shape(target.positions, rest, f"{where}: mesh"))
            spec = pb.TargetRig(combination=[str(d) for d in target.combination])
            for i, (weight, positions) in enumerate(target.inbetweens):
                spec.inbetween_weights.append(float(weight))
                inbetweens.append(self._same_shape(positions, rest, f"{where}: inbetweens[{i}].mesh"))
            if target.mask is not None:
                mask = arrays.as_array(target.mask, f"{where}: mask", np.float64).reshape(-1)
                if len(mask) != len(rest):
                    raise invalid_argument(f"{where}: mask: {len(mask)} values, but the rest mesh has {len(rest)} "
                                           "vertices")
                spec.has_mask = True
                masks[index] = np.ascontiguousarray(mask, dtype="<f8").tobytes()
            specs.append(spec)
        fixed = [int(v) for v in (*rig.fixed_vertices, *fixed_vertices)]
        header = pb.UploadHeader(name=name, vertex_count=len(rest), face_count=len(faces),
                                 target_names=[t.name for t in rig.targets], targets=specs,
                                 options=pb.BuildOptions(fixed_vertices=fixed, **options))
        try:
            return self._upload(header, faces, shapes_ + inbetweens, masks, on_progress)
        except SpringblendError as error:
            raise SpringblendError(error.code, f"{rig.path}: {error.message}") from None

    @staticmethod
    def _same_shape(positions, rest, what):
        points = arrays.as_points(positions, what)
        if points.shape != rest.shape:
            raise invalid_argument(f"{what}: {len(points)} vertices, but the rest mesh has {len(rest)}")
        return points

    def _upload(self, header, faces, shapes_, masks, on_progress=None):
        """Streams the header, the faces, every shape's positions (rest, targets, in-betweens) and the masks
        ({target index: float64 bytes}); with on_progress, follows the build while the call waits."""
        def chunks():
            yield pb.UploadChunk(header=header)
            yield from self._pieces(pb.MeshPiece.FACES, 0, faces.tobytes(), len(faces), 12)
            for shape, points in enumerate(shapes_):
                yield from self._pieces(pb.MeshPiece.POSITIONS, shape, arrays.pack_float64(points), len(points), 24)
            for target, data in masks.items():
                yield from self._pieces(pb.MeshPiece.MASK, target, data, len(data) // 8, 8)

        # Routed as its solves will be: by the id the server will give it.
        character_id = routing.character_id(header, faces, shapes_, masks)
        if on_progress is None:
            return self._call(self._characters.UploadCharacter, chunks(), character_id)
        try:
            call = self._characters.UploadCharacter.future(chunks(), timeout=self.timeout,
                                                           metadata=self._metadata(character_id))
        except grpc.RpcError as error:
            raise self._error(error) from None
        try:
            self._follow_build(call, on_progress)
            return call.result()
        except grpc.RpcError as error:
            raise self._error(error) from None
        finally:
            call.cancel()  # a no-op once the call has ended; otherwise (the callback raised) the build stops

    def _follow_build(self, call, on_progress):
        """Calls on_progress while the upload's build runs, as the C++ client's UploadRig does: the character's
        id arrives as initial metadata once the server has checked the pieces (not at all when it refuses
        them), then GetCharacter(no_wait) answers with the build's progress at once."""
        ended = threading.Event()
        call.add_done_callback(lambda _: ended.set())
        character_id = dict(call.initial_metadata() or ()).get(CHARACTER_ID_METADATA, "")
        if isinstance(character_id, bytes):
            character_id = character_id.decode()
        request = pb.GetCharacterRequest(id=character_id, no_wait=True)
        while character_id and not ended.wait(PROGRESS_INTERVAL):
            try:
                state = self._characters.GetCharacter(request, timeout=5.0, metadata=self._metadata(character_id))
            except grpc.RpcError:
                continue  # progress is best effort: the upload's own answer says how it went
            if state.state == pb.CHARACTER_STATE_BUILDING and not ended.is_set():
                on_progress(character_id, state.build)

    def _pieces(self, kind, shape, data, elements, size):
        per_piece = max(1, self.piece_bytes // size)
        for first in range(0, elements, per_piece):
            count = min(per_piece, elements - first)
            piece = pb.MeshPiece(kind=kind, shape=shape, offset=first, data=data[first * size:(first + count) * size])
            yield pb.UploadChunk(piece=piece)

    def resolve(self, character):
        """A character's full id from its id, 12 or more of its first hex digits (as the server's logs show
        them), or its name, when that names exactly one character the server lists. Every method that takes a
        character_id resolves it so."""
        given = str(character)
        is_hex = bool(given) and set(given) <= set("0123456789abcdef")
        if is_hex and len(given) == 64:
            return given
        listed = self.list()
        found = [c.id for c in listed if is_hex and len(given) >= 12 and c.id.startswith(given)]
        found = found or [c.id for c in listed if c.name == given]
        if len(found) == 1:
            return found[0]
        if not found:
            raise SpringblendError(grpc.StatusCode.NOT_FOUND,
                                   f"character '{given}': no character on the server has this "
                                   f"{'id prefix or name' if is_hex and len(given) >= 12 else 'name'} (give a full "
                                   "id, 12 or more of its hex digits, or a name; Client.list() shows them)")
        raise invalid_argument(f"character '{given}' names {len(found)} characters "
                               f"({', '.join(i[:16] for i in found)}): give more of the id")

    def get(self, character_id, with_faces=False, no_wait=False):
        """The Character message of an uploaded character; with_faces adds its packed triangles. It waits for a
        character being built (within the timeout); no_wait answers at once with its state: READY with the
        summary, BUILDING with the build's progress (.build), or STORED (only in the server's cache directory)."""
        character_id = self.resolve(character_id)
        return self._call(self._characters.GetCharacter,
                          pb.GetCharacterRequest(id=character_id, with_faces=with_faces, no_wait=no_wait),
                          character_id)

    def faces(self, character_id):
        """The character's triangles as a #F by 3 int32 array."""
        packed = self.get(character_id, with_faces=True).faces
        return np.frombuffer(packed, dtype="<i4").reshape(-1, 3)

    def list(self):
        """Every character the server knows (built ones carry their summary)."""
        return list(self._call(self._characters.ListCharacters, pb.ListCharactersRequest()).characters)

    def delete(self, character_id):
        """Removes a character from the server's memory and cache directory."""
        character_id = self.resolve(character_id)
        self._call(self._characters.DeleteCharacter, pb.DeleteCharacterRequest(id=character_id), character_id)

    def healthy(self, timeout=5.0):
        """True when the server's standard health service reports SERVING (False when unreachable)."""
        try:
            return self.health(timeout) == "SERVING"
        except SpringblendError:
            return False

    def health(self, timeout=5.0):
        """What the server's standard health service reports: "SERVING", or "NOT_SERVING" while it drains.
        Raises SpringblendError (UNAVAILABLE, saying so) when no server answers at the address. Needs no token."""
        try:
            response = self._health(health_pb2.HealthCheckRequest(), timeout=timeout)
        except grpc.RpcError as error:
            raise self._error(error) from None
        return health_pb2.HealthCheckResponse.ServingStatus.Name(response.status)

    # ---------------------------------------------------------------------------------------------------
    # Solving

    def solve(self, character_id, weights, colliders=(), collider_transforms=None, pins=None, on_frame=None,
              **options):
        """Solves frames and returns a Solution with all of them (see solve_frames for the arguments)."""
        frames = []
        for frame in self.solve_frames(character_id, weights, colliders, collider_transforms, pins, **options):
            if on_frame is not None:
                on_frame(frame)
            frames.append(frame)
        normals = np.stack([f.normals for f in frames]) if frames and frames[0].normals is not None else None
        return Solution(positions=np.stack([f.positions for f in frames]), normals=normals,
                        summaries=[f.summary for f in frames])

    def solve_frames(self, character_id, weights, colliders=(), collider_transforms=None, pins=None,
                     tolerance=0.0, max_iterations=0, linear=False, normals=False, certify_minimum=False, mix="",
                     linear_targets=None):
        """Streams a Solve: yields one SolvedFrame per frame as the server finishes it.

        Args:
            character_id: the id upload returned (or 12 or more of its hex digits, or its name: see resolve).
            weights: #frames by #targets (or one frame's #targets), in the character's target order; or by name,
                a dict {"jawOpen": 0.7, ...} per frame (or one dict), the targets not named at 0. Unknown names
                are refused, naming the character's targets.
            colliders: Collider messages (see springblend.colliders), fixed for the whole request.
            collider_transforms: None, or per frame a sequence with one transform per collider: a Transform
                message or a (translation, (w, x, y, z)) pair.
            pins: None, or per frame a mapping vertex -> position (or None).
            tolerance, max_iterations, linear, normals: SolveOptions (zero means the server's default).
            certify_minimum: have the server check each converged answer is a local minimum (about one
                factorization more per frame): summary.minimum is "minimum", "not_a_minimum" or "not_checked".
            mix: how a frame that moves several targets combines them: "superposed" (the server's default, also
                "") or "rest-lengths" (the paper's blend of rest lengths).
            linear_targets: None (the server's default correctives, ARKit's mouthClose where the character has
                it), or the names of the targets added as linear deltas with the superposed mix ([] for none).
        """
        character_id = self.resolve(character_id)
        request = pb.SolveRequest(
            character_id=character_id, colliders=list(colliders),
            options=pb.SolveOptions(residual_tolerance=float(tolerance), max_iterations=int(max_iterations),
                                    linear=bool(linear), with_normals=bool(normals),
                                    certify_minimum=bool(certify_minimum), mix=str(mix),
                                    linear_targets=(None if linear_targets is None else
                                                    pb.LinearTargets(names=[str(n) for n in linear_targets]))),
            frames=_frame_requests(self._by_position(character_id, weights), collider_transforms, pins))
        call = self._solves.Solve(request, timeout=self.timeout, metadata=self._metadata(character_id))
        expected = len(request.frames)
        received = 0
        vertices = None
        try:
            for frame in call:
                # The server answers every frame once, in order: anything else is not a solution of this request.
                if frame.index >= expected:
                    raise bad_answer(f"frame {frame.index} came, but the request has {expected} frames")
                if frame.index != received:
                    raise bad_answer(f"frame {frame.index} came where frame {received} of {expected} was due")
                solved = _decode(frame, vertices)
                vertices = solved.positions.shape[0]
                received += 1
                yield solved
            if received != expected:
                raise bad_answer(f"the stream ended after {received} of {expected} frames")
        except grpc.RpcError as error:
            raise self._error(error) from None
        finally:
            call.cancel()  # a no-op once the stream has ended; a caller that stops early ends it on the server

    def read_take(self, character_id, take, map=None, lost="hold", warn=True):  # noqa: A002 - the CLI's --map
        """A captured take (a Live Link Face CSV's path, or a springblend.performance.Take) matched to the
        character's targets: a springblend.performance.Performance whose weights solve() and solve_frames() take
        as they are, and whose report says what was left out (also given as one TakeWarning). map, lost: as
        springblend.performance.match (the CLI's --map and --lost)."""
        return performance.match(take, self.target_names(self.resolve(character_id)), map=map, lost=lost, warn=warn)

    def solve_take(self, character_id, take, map=None, lost="hold", **options):  # noqa: A002
        """Streams the solve of a captured take, as solve_frames streams frames: take is a path (read and matched
        to the character's targets with map and lost, see read_take) or a Performance read for this character.
        options: those of solve_frames (colliders, collider_transforms, pins, linear, ...)."""
        if not isinstance(take, performance.Performance):
            take = self.read_take(character_id, take, map=map, lost=lost)
        names = self.target_names(self.resolve(character_id))
        if list(take.target_names) != names:
            raise invalid_argument(f"solve_take: the performance was matched to targets {take.target_names}, not "
                                   f"this character's {names}: read it with read_take for this character")
        return self.solve_frames(character_id, take.weights, **options)

    def interactive(self, character_id, colliders=(), tolerance=0.0, max_iterations=0, linear=False,
                    normals=False, previews=False):
        """Opens an interactive (slider) session; see InteractiveSession. previews=True: each frame is first
        answered at once by its preview (the rig's prediction; summary.converged False, termination "preview"),
        then by its solve unless a newer frame overtakes it."""
        character_id = self.resolve(character_id)
        start = pb.InteractiveStart(
            character_id=character_id, colliders=list(colliders),
            options=pb.SolveOptions(residual_tolerance=float(tolerance), max_iterations=int(max_iterations),
                                    linear=bool(linear), with_normals=bool(normals)),
            previews=bool(previews))
        return InteractiveSession(self._solves, start, self.timeout, self._metadata(character_id), self._error,
                                  lambda weights: self._by_position(character_id, weights))

    def target_names(self, character_id):
        """The character's targets that take weights, in weight order (asked once per id: an id names one
        character's content for good)."""
        names = self._target_names.get(character_id)
        if names is None:
            names = list(self.get(character_id).target_names)
            self._target_names[character_id] = names
        return names

    def _by_position(self, character_id, weights):
        """Weights given by name (a dict per frame, or one dict) as rows in the character's target order."""
        frames = [weights] if isinstance(weights, dict) else weights
        if not isinstance(frames, (list, tuple)) or not frames or not any(isinstance(f, dict) for f in frames):
            return weights
        names = self.target_names(character_id)
        rows = []
        for i, frame in enumerate(frames):
            where = "weights" if isinstance(weights, dict) else f"weights[{i}]"
            if not isinstance(frame, dict):
                raise invalid_argument(f"{where}: give every frame's weights by name (a dict) or none")
            row = [0.0] * len(names)
            for name, value in frame.items():
                if name not in names:
                    raise invalid_argument(f"{where}: '{name}' is not a target of this character (targets: "
                                           f"{', '.join(names) or 'none'})")
                try:
                    row[names.index(name)] = float(value)
                except (TypeError, ValueError):
                    raise invalid_argument(f"{where}['{name}']: expected a number, got {value!r}") from None
            rows.append(row)
        return rows[0] if isinstance(weights, dict) else rows

    def _call(self, method, request, character_id=""):
        try:
            return method(request, timeout=self.timeout, metadata=self._metadata(character_id))
        except grpc.RpcError as error:
            raise self._error(error) from None

    def _metadata(self, character_id):
        """The routing header and the token of a call."""
        token = (("authorization", f"Bearer {self._token}"),) if self._token else ()
        return _route(character_id) + token

    def _error(self, rpc_error):
        """A SpringblendError whose message says what to do where gRPC's alone would not."""
        error = SpringblendError.from_rpc_error(rpc_error)
        code, message = error.code, error.message
        if code == grpc.StatusCode.UNAVAILABLE and "shutting down" not in message:
            message = f"cannot reach a springblend server at {self.address} ({self.address_source}): {message}"
            if not self.tls:
                message += "; a server using TLS needs tls=True or tls_ca"
            elif any(word in message for word in ("SSL", "ssl", "handshake", "certificate")):
                message += ("; the TLS handshake failed: tls_ca must name the CA that signed the server's "
                            "certificate, tls_server_name a name it carries, and a server requiring client "
                            "certificates needs tls_cert and tls_key")
        elif code == grpc.StatusCode.UNAUTHENTICATED:
            message += (f"; pass token= to springblend.Client or set ${TOKEN_VARIABLE}" if not self._token else
                        f"; check token= or ${TOKEN_VARIABLE}")
        elif code == grpc.StatusCode.DEADLINE_EXCEEDED and message == "Deadline Exceeded":
            message = (f"the call did not finish within the client's timeout of {self.timeout:g} s; pass a larger "
                       "timeout= (None: no limit)")
        return SpringblendError(code, message)


class InteractiveSession:
    """A slider session: send() frames as the artist moves; iterate (or next_frame()) for answers.

    The server answers the newest frame it has and drops overtaken ones, so not every sent index comes back.
    close() half-closes; iterating then drains the remaining answers until the stream ends. Use it as a
    context manager to close (and cancel anything unread) on the way out.
    """

    _END = object()

    def __init__(self, stub, start, timeout, metadata, explain, by_position=lambda weights: weights):
        self._outbox = queue.Queue()
        self._outbox.put(pb.InteractiveRequest(start=start))
        self._sent = 0
        self._closed = False
        self._explain = explain
        self._by_position = by_position
        self._responses = stub.Interactive(self._requests(), timeout=timeout, metadata=metadata)

    def _requests(self):
        while True:
            item = self._outbox.get()
            if item is self._END:
                return
            yield item

    def send(self, weights, collider_transforms=None, pins=None):
        """Queues one frame (weights in target order, or a dict by target name; one transform per collider or
        None; pins mapping or None) and returns its index, the index its SolvedFrame will carry."""
        if self._closed:
            raise invalid_argument("send: the session is closed")
        transforms = None if collider_transforms is None else [collider_transforms]
        frame_pins = None if pins is None else [pins]
        (request,) = _frame_requests([np.ravel(self._by_position(weights))], transforms, frame_pins)
        index = self._sent
        self._sent += 1  # before the frame goes: its answer may come back at once
        self._outbox.put(pb.InteractiveRequest(frame=request))
        return index

    def close(self):
        """Half-closes: no more frames; the stream ends once the last one is answered."""
        if not self._closed:
            self._closed = True
            self._outbox.put(self._END)

    def cancel(self):
        """Abandons the session at once."""
        self.close()
        self._responses.cancel()

    def next_frame(self):
        """Blocks for the next SolvedFrame; None once the stream has ended."""
        try:
            frame = next(self._responses)
            if frame.index >= self._sent:
                raise bad_answer(f"frame {frame.index} came, but the session has sent {self._sent} frames")
            return _decode(frame)
        except StopIteration:
            return None
        except grpc.RpcError as error:
            raise self._explain(error) from None

    def __iter__(self):
        while (frame := self.next_frame()) is not None:
            yield frame

    def __enter__(self):
        return self

    def __exit__(self, exc_type, *exc):
        if exc_type is None:
            self.close()
        else:
            self.cancel()


def _route(character_id):
    return ((CHARACTER_HEADER, character_id),) if character_id else ()


def _resolve_address(address):
    """(address, where it came from): the argument, $SPRINGBLEND_SERVER, or 127.0.0.1:50051."""
    if address:
        return address, "given"
    if os.environ.get(SERVER_VARIABLE):
        return os.environ[SERVER_VARIABLE], f"${SERVER_VARIABLE}"
    return DEFAULT_SERVER, "the default"


def _read_pem(what, path):
    """The bytes of a PEM file (None when no path is given); a missing or non-PEM file is named."""
    if not path:
        return None
    try:
        with open(path, "rb") as pem:
            data = pem.read()
    except OSError as error:
        raise invalid_argument(f"{what}: cannot read {path}: {error.strerror or error}") from None
    if b"-----BEGIN " not in data:
        raise invalid_argument(f"{what}: {path} is not a PEM file")
    return data


def _decode(frame, vertices=None):
    """A SolvedFrame message as numpy arrays; SpringblendError (DATA_LOSS) when its arrays are not #V by 3 finite
    float32 (V = vertices when given: the frames before it), normals when sent of the positions' shape."""
    where = f"frame {frame.index}"
    try:
        positions = arrays.unpack_float32(frame.positions)
        normals = arrays.unpack_float32(frame.normals) if frame.normals else None
    except ValueError as error:
        raise bad_answer(f"{where}: {error}") from None
    if positions.shape[0] == 0 or (vertices is not None and positions.shape[0] != vertices):
        raise bad_answer(f"{where} has {positions.shape[0]} vertices, the frames before it {vertices}"
                         if vertices is not None else f"{where} has no vertices")
    if normals is not None and normals.shape != positions.shape:
        raise bad_answer(f"{where} has {normals.shape[0]} normals for {positions.shape[0]} vertices")
    for name, values in (("positions", positions), ("normals", normals)):
        if values is not None and not np.all(np.isfinite(values)):
            vertex = int(np.argwhere(~np.isfinite(values))[0][0])
            raise bad_answer(f"{where}: {name} of vertex {vertex} are not finite")
    return SolvedFrame(index=frame.index, positions=positions, normals=normals, summary=frame.summary)


def _frame_requests(weights, collider_transforms, pins):
    weights = arrays.as_array(weights, "weights (one row of #targets numbers per frame)", np.float64)
    if weights.ndim == 1:
        weights = weights[np.newaxis, :]
    if weights.ndim != 2 or weights.shape[0] == 0:
        raise invalid_argument(f"weights: expected #frames by #targets, got shape {weights.shape}")
    count = weights.shape[0]
    for what, per_frame in (("collider_transforms", collider_transforms), ("pins", pins)):
        if per_frame is not None and len(per_frame) != count:
            raise invalid_argument(f"{what}: one entry per frame ({count}), got {len(per_frame)}")
    frames = []
    for i in range(count):
        frame = pb.FrameRequest(weights=weights[i].tolist())
        if collider_transforms is not None:
            for motion in collider_transforms[i] or ():
                frame.collider_transforms.append(
                    motion if isinstance(motion, pb.Transform) else shapes.transform(*motion))
        if pins is not None and pins[i]:
            frame.pins.extend(shapes.pin(v, p) for v, p in pins[i].items())
        frames.append(frame)
    return frames
