"""The Python client against a real springblend-server with TLS and tokens: the CLI's options (tls_ca, tls_cert,
tls_key, tls_server_name, token) and environment variables ($SPRINGBLEND_SERVER, $SPRINGBLEND_TOKEN); a missing
token, a wrong CA, plaintext to a TLS port and a missing CA file each fail with a message saying what to fix."""

import os
import tempfile
import unittest
from unittest import mock

import grpc

import springblend
import springblend_testing as testing

FULL_TOKEN, SOLVE_TOKEN = "python-full-secret", "python-solve-secret"


def tls_server(certificates, tokens_file, *extra):
    return testing.Server(arguments=["--tls-cert", certificates.file("server.pem"), "--tls-key",
                                     certificates.file("server.key"), "--tokens-file", tokens_file, *extra])


class SecuredServerTest(unittest.TestCase):
    @classmethod
    def setUpClass(cls):
        cls.certificates = testing.Certificates()
        cls.tokens = os.path.join(cls.certificates.directory, "tokens")
        with open(cls.tokens, "w") as out:
            out.write(f"full {FULL_TOKEN}\nsolve {SOLVE_TOKEN}\n")
        cls.server = tls_server(cls.certificates, cls.tokens)
        cls.ca = cls.certificates.file("ca.pem")
        cls.rest, cls.faces, cls.targets = testing.cylinder()

    @classmethod
    def tearDownClass(cls):
        cls.server.stop()
        cls.certificates.close()

    def client(self, **options):
        options.setdefault("tls_ca", self.ca)
        options.setdefault("timeout", 60)
        return springblend.Client(self.server.address, **options)

    def refusal(self, call):
        with self.assertRaises(springblend.SpringblendError) as caught:
            call()
        return caught.exception

    def test_list_upload_and_solve_with_the_ca_and_a_token(self):
        with self.client(token=FULL_TOKEN) as client:
            self.assertEqual(client.health(), "SERVING")
            character = client.upload(self.rest, self.faces, self.targets, name="cylinder")
            self.assertIn(character.id, [c.id for c in client.list()])
            solution = client.solve(character.id, [[0.5, 0.25], [1.0, 0.5]])
            self.assertEqual(solution.positions.shape, (2, len(self.rest), 3))
            self.assertTrue(solution.converged, [s.message for s in solution.summaries])
            with client.interactive(character.id) as session:
                session.send([0.25, 0.0])
                session.close()
                self.assertTrue(any(frame.summary.converged for frame in session))
        # A token of the solve role solves but may not upload.
        with self.client(token=SOLVE_TOKEN) as solver:
            self.assertEqual(len(solver.solve(character.id, [0.5, 0.5]).summaries), 1)
            denied = self.refusal(lambda: solver.upload(self.rest, self.faces, self.targets))
            self.assertEqual(denied.code, grpc.StatusCode.PERMISSION_DENIED)

    def test_the_cli_environment_variables_give_the_address_and_the_token(self):
        environment = {"SPRINGBLEND_SERVER": self.server.address, "SPRINGBLEND_TOKEN": FULL_TOKEN}
        with mock.patch.dict(os.environ, environment):
            with springblend.Client(tls_ca=self.ca, timeout=60) as client:
                self.assertEqual(client.address, self.server.address)
                self.assertEqual(client.address_source, "$SPRINGBLEND_SERVER")
                client.list()
            # An explicit empty token sends none, whatever the environment says.
            with springblend.Client(tls_ca=self.ca, timeout=60, token="") as anonymous:
                self.assertEqual(self.refusal(anonymous.list).code, grpc.StatusCode.UNAUTHENTICATED)
        with mock.patch.dict(os.environ, {"SPRINGBLEND_SERVER": ""}):
            with springblend.Client() as default:
                self.assertEqual(default.address, "127.0.0.1:50051")

    def test_without_the_token_the_error_says_to_set_it(self):
        with mock.patch.dict(os.environ, {"SPRINGBLEND_TOKEN": ""}), self.client() as client:
            self.assertEqual(client.health(), "SERVING", "health needs no token")
            error = self.refusal(client.list)
            self.assertEqual(error.code, grpc.StatusCode.UNAUTHENTICATED)
            self.assertIn("authorization: Bearer TOKEN", error.message)  # the server's words
            self.assertIn("pass token= to springblend.Client or set $SPRINGBLEND_TOKEN", error.message)
            error = self.refusal(lambda: client.solve("a" * 64, [0.5, 0.5]))
            self.assertEqual(error.code, grpc.StatusCode.UNAUTHENTICATED)
        with self.client(token="not-a-token") as wrong:
            error = self.refusal(wrong.list)
            self.assertEqual(error.code, grpc.StatusCode.UNAUTHENTICATED)
            self.assertIn("check token= or $SPRINGBLEND_TOKEN", error.message)

    def test_a_wrong_ca_or_name_or_plaintext_cannot_reach_the_server(self):
        with self.client(tls_ca=self.certificates.file("rogue-ca.pem"), token=FULL_TOKEN, timeout=10) as rogue:
            error = self.refusal(rogue.list)
            self.assertEqual(error.code, grpc.StatusCode.UNAVAILABLE)
            self.assertIn(f"cannot reach a springblend server at {self.server.address}", error.message)
            self.assertIn("tls_ca must name the CA that signed the server's certificate", error.message)
            self.assertFalse(rogue.healthy(timeout=5))
        with self.client(tls_server_name="elsewhere.example", token=FULL_TOKEN, timeout=10) as misnamed:
            self.assertEqual(self.refusal(misnamed.list).code, grpc.StatusCode.UNAVAILABLE)
        with self.client(tls_server_name="localhost", token=FULL_TOKEN) as by_name:
            by_name.list()
        with springblend.Client(self.server.address, token=FULL_TOKEN, timeout=10) as plaintext:
            error = self.refusal(plaintext.list)
            self.assertEqual(error.code, grpc.StatusCode.UNAVAILABLE)
            self.assertIn("a server using TLS needs tls=True or tls_ca", error.message)

    def test_missing_or_bad_tls_files_are_named(self):
        missing = os.path.join(self.certificates.directory, "missing-ca.pem")
        error = self.refusal(lambda: springblend.Client(self.server.address, tls_ca=missing))
        self.assertEqual(error.code, grpc.StatusCode.INVALID_ARGUMENT)
        self.assertIn(f"tls_ca: cannot read {missing}", error.message)
        with tempfile.NamedTemporaryFile("w", suffix=".pem") as text:
            text.write("not a certificate\n")
            text.flush()
            error = self.refusal(lambda: springblend.Client(self.server.address, tls_ca=text.name))
            self.assertIn(f"tls_ca: {text.name} is not a PEM file", error.message)
        error = self.refusal(lambda: springblend.Client(self.server.address, tls_cert=self.certificates.file(
            "client.pem")))
        self.assertIn("tls_cert and tls_key go together", error.message)


class MutualTlsTest(unittest.TestCase):
    def test_a_client_certificate_from_the_servers_ca_is_served(self):
        with testing.Certificates() as certificates:
            tokens = certificates.file("tokens")
            with open(tokens, "w") as out:
                out.write(f"full {FULL_TOKEN}\n")
            with tls_server(certificates, tokens, "--tls-client-ca", certificates.file("ca.pem")) as server:
                options = dict(tls_ca=certificates.file("ca.pem"), token=FULL_TOKEN, timeout=10)
                with springblend.Client(server.address, tls_cert=certificates.file("client.pem"),
                                        tls_key=certificates.file("client.key"), **options) as trusted:
                    self.assertEqual(trusted.list(), [])
                with springblend.Client(server.address, **options) as anonymous:
                    with self.assertRaises(springblend.SpringblendError) as caught:
                        anonymous.list()
                    self.assertEqual(caught.exception.code, grpc.StatusCode.UNAVAILABLE)


if __name__ == "__main__":
    unittest.main()
