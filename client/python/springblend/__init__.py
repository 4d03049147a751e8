"""springblend: the Python client of the springblend farm server (physically based blendshapes).

Needs only Debian's python3-grpcio, python3-protobuf and python3-numpy, so it runs inside a DCC's Python.
Install it (pip install client/python, docs/python.md) or put the build's python directory
(build/release/python) on sys.path, then:

    import springblend
    with springblend.Client("127.0.0.1:50051") as client:
        character = client.upload(rest, faces, {"bend": bend, "twist": twist}, name="arm")
        solution = client.solve(character.id, [[0.5, 0.0], [1.0, 0.2]],
                                colliders=[springblend.colliders.sphere((0, 1, 0), 0.3)])
        solution.positions  # #frames by #V by 3 float32
        solution.write_pc2("shot.pc2")  # a point cache for the DCC's Mesh Cache (frame = index + 1)
        face = client.upload_rig("face/rig.json")  # in-betweens, masks, combinations (springblend.rigfile)
        take = client.read_take(face.id, "take.csv")  # a captured performance (springblend.performance)
        client.solve(face.id, take.weights).write_pc2("take.pc2", take.start_frame)
"""

from springblend import _dependencies

_dependencies.check()  # a missing numpy, grpcio or protobuf is named, with how to install it

from springblend import colliders, performance, pointcache, rigfile  # noqa: E402
from springblend._version import __version__  # noqa: E402
from springblend._generated import pb  # noqa: E402
from springblend.client import (  # noqa: E402
    CHARACTER_HEADER, CHARACTER_ID_METADATA, Client, InteractiveSession, Solution, SolvedFrame)
from springblend.errors import SpringblendError  # noqa: E402

__all__ = ["CHARACTER_HEADER", "CHARACTER_ID_METADATA", "Client", "InteractiveSession", "Solution", "SolvedFrame",
           "SpringblendError", "__version__", "colliders", "pb", "performance", "pointcache", "rigfile"]
