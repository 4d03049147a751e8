"""The Blender add-on against a secured farm, headless in a real Blender: starts a springblend server with TLS
and tokens, then runs Blender (secure_in_blender.py), which sets the add-on's preferences (CA bundle, token) and
checks, uploads, bakes and previews live through them; a missing token, a missing CA file and a wrong CA come
back as reports saying what to fix.

Run by CTest (tests/CMakeLists.txt) with /usr/bin/python3; needs $BLENDER, $SPRINGBLEND_ADDON_ZIP and what
springblend_testing reads. Fails, never skips, when Blender is missing.
"""

import os
import pathlib
import sys
import tempfile

sys.path.insert(0, str(pathlib.Path(__file__).parent))
import blender_runner as runner  # noqa: E402
from blender_runner import testing  # noqa: E402

FRAMES = [1, 2]
WEIGHTS = [[0.3, 0.1], [0.6, 0.3]]
BALL_LOCATIONS = [[-1.9, 0.75, 0.75], [-1.8, 0.75, 0.75]]
TOKEN = "blender-secret"


def main():
    runner.blender_executable()
    with testing.Certificates() as certificates, \
            tempfile.TemporaryDirectory(prefix="springblend-blender-") as directory:
        tokens = os.path.join(directory, "tokens")
        with open(tokens, "w") as out:
            out.write(f"full {TOKEN}\n")
        arguments = ["--tls-cert", certificates.file("server.pem"), "--tls-key", certificates.file("server.key"),
                     "--tokens-file", tokens]
        with testing.Server(arguments=arguments) as server:
            config = dict(runner.scene_config(server, WEIGHTS, BALL_LOCATIONS, FRAMES), token=TOKEN,
                          ca=certificates.file("ca.pem"), rogue_ca=certificates.file("rogue-ca.pem"),
                          missing_ca=os.path.join(directory, "missing-ca.pem"))
            environment = {k: os.environ.pop(k) for k in ("SPRINGBLEND_TOKEN", "SPRINGBLEND_SERVER") if k in os.environ}
            try:
                runner.run_blender("secure_in_blender.py", config, directory, server)
            finally:
                os.environ.update(environment)
    print("secure_test: OK")


if __name__ == "__main__":
    main()
