"""The springblend Python client against a real server: upload from arrays, solve into arrays equal to the
C++ CLI's output, an interactive session, health, and errors carrying the server's status and message."""

import json
import os
import tempfile
import unittest

import grpc
import numpy as np

import springblend
from springblend.colliders import box, mesh, sphere
import springblend_testing as testing

# Frames of the two cylinder targets with a ball in the way (the quickstart's obstacle), solved by both the
# Python client and the CLI.
WEIGHTS = [[0.2, 0.1], [0.5, 0.25], [0.8, 0.4]]
BALL = ((-1.7, 0.75, 0.75), 0.3)


class ClientTest(unittest.TestCase):
    @classmethod
    def setUpClass(cls):
        cls.server = testing.Server()
        cls.client = springblend.Client(cls.server.address, timeout=120)
        cls.rest, cls.faces, cls.targets = testing.cylinder()
        cls.character = cls.client.upload(cls.rest, cls.faces, cls.targets, name="cylinder")
        cls.diagonal = testing.bounding_box_diagonal(cls.rest)

    @classmethod
    def tearDownClass(cls):
        cls.client.close()
        cls.server.stop()

    def test_health(self):
        self.assertTrue(self.client.healthy())
        with springblend.Client("127.0.0.1:1", timeout=5) as nobody:
            self.assertFalse(nobody.healthy(timeout=2))

    def test_upload_from_arrays(self):
        c = self.character
        self.assertRegex(c.id, "^[0-9a-f]{64}$")
        self.assertEqual(list(c.target_names), list(testing.CYLINDER_TARGETS))
        self.assertEqual(c.summary.surface_vertices, len(self.rest))
        self.assertEqual(c.summary.faces, len(self.faces))
        # Same meshes (names are not part of the id): the CLI's upload of the OBJ files is a cache hit.
        self.assertEqual(testing.cli_upload_cylinder(self.server.address), c.id)
        again = self.client.upload(self.rest, self.faces, list(self.targets.values()),
                                   target_names=list(self.targets))
        self.assertTrue(again.cache_hit)
        self.assertEqual(again.id, c.id)

    def test_small_pieces_give_the_same_character(self):
        with springblend.Client(self.server.address, piece_bytes=1000) as small:
            self.assertEqual(small.upload(self.rest, self.faces, self.targets).id, self.character.id)

    def test_get_list_and_faces(self):
        self.assertEqual(self.client.get(self.character.id).name, "cylinder")
        self.assertIn(self.character.id, [c.id for c in self.client.list()])
        np.testing.assert_array_equal(self.client.faces(self.character.id), self.faces)

    def test_solve_equals_cli(self):
        solution = self.client.solve(self.character.id, WEIGHTS, colliders=[sphere(*BALL)])
        self.assertEqual(solution.positions.shape, (len(WEIGHTS), len(self.rest), 3))
        self.assertEqual(solution.positions.dtype, np.float32)
        self.assertTrue(solution.converged, [s.message for s in solution.summaries])
        self.assertGreater(sum(s.contacts for s in solution.summaries), 0, "the ball should touch the cylinder")
        with tempfile.TemporaryDirectory() as directory:
            cli_positions, _ = testing.cli_solve(
                self.server.address, self.character.id, [{"weights": w} for w in WEIGHTS],
                ["sphere:{},{},{},{}".format(*BALL[0], BALL[1])], directory)
        error = np.abs(solution.positions - cli_positions).max()
        self.assertLessEqual(error, 1e-5 * self.diagonal)

    def test_cli_and_python_point_caches_hold_the_solve(self):
        weights = WEIGHTS
        solution = self.client.solve(self.character.id, weights, colliders=[sphere(*BALL)])
        with tempfile.TemporaryDirectory() as directory:
            scene = os.path.join(directory, "scene.json")
            with open(scene, "w") as out:
                json.dump({"colliders": ["sphere:{},{},{},{}".format(*BALL[0], BALL[1])],
                           "frames": [{"weights": w} for w in weights]}, out)
            cli_cache = os.path.join(directory, "cli.pc2")
            testing.cli("solve", "--server", self.server.address, "--character", self.character.id,
                        "--frames", scene, "--out", cli_cache)
            solution.write_pc2(os.path.join(directory, "python.pc2"))
            from_cli = springblend.pointcache.read_pc2(cli_cache)
            from_python = springblend.pointcache.read_pc2(os.path.join(directory, "python.pc2"))
        for cache in (from_cli, from_python):
            self.assertEqual((cache.start_frame, cache.sample_rate), (1.0, 1.0))
            self.assertEqual(cache.positions.shape, (len(weights), len(self.rest), 3))
            self.assertLessEqual(np.abs(cache.positions - solution.positions).max(), 1e-6 * self.diagonal)

    def test_mesh_collider_as_arrays_gives_the_frames_of_obj_text(self):
        # A closed box in the cylinder's way, corners exact in float32 (the text is read as float32).
        corners = np.array([[x, y, z] for x in (-2.0, -1.5) for y in (0.5, 1.0) for z in (0.5, 1.0)])
        quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
        triangles = [t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))]
        by_arrays = self.client.solve(self.character.id, WEIGHTS, colliders=[mesh(corners, triangles)])
        by_text = self.client.solve(self.character.id, WEIGHTS, colliders=[mesh(corners, triangles, as_obj_text=True)])
        np.testing.assert_array_equal(by_arrays.positions, by_text.positions)
        self.assertGreater(sum(s.contacts for s in by_arrays.summaries), 0, "the box should touch the cylinder")
        with self.assertRaises(springblend.SpringblendError) as caught:
            self.client.solve(self.character.id, WEIGHTS, colliders=[mesh(corners, triangles[:-1])])
        self.assertEqual(caught.exception.code, grpc.StatusCode.INVALID_ARGUMENT)
        self.assertIn("colliders[0]", caught.exception.message)

    def test_solve_streams_frames_with_moving_colliders_and_pins(self):
        translations = [[(0.0, 0.0, 0.0), (1.0, 0.0, 0.0, 0.0)], [(0.1, 0.0, 0.0), (1.0, 0.0, 0.0, 0.0)]]
        frames = list(self.client.solve_frames(
            self.character.id, WEIGHTS[:2], colliders=[sphere(*BALL)],
            collider_transforms=[[t] for t in translations], pins=[{0: self.rest[0]}, None], normals=True))
        self.assertEqual([f.index for f in frames], [0, 1])
        self.assertEqual(frames[0].normals.shape, (len(self.rest), 3))
        self.assertEqual(frames[0].summary.pins, 1)
        np.testing.assert_allclose(frames[0].positions[0], self.rest[0], atol=1e-5 * self.diagonal)

    def test_certified_frames_say_they_are_minima(self):
        plain = self.client.solve(self.character.id, WEIGHTS[:2])
        certified = self.client.solve(self.character.id, WEIGHTS[:2], certify_minimum=True)
        self.assertEqual([s.minimum for s in plain.summaries], ["not_checked"] * 2)
        self.assertEqual([s.minimum for s in certified.summaries], ["minimum"] * 2)
        self.assertTrue(all(s.certify_ms > 0 for s in certified.summaries))
        np.testing.assert_array_equal(certified.positions, plain.positions)

    def test_mix_models_and_linear_targets_reach_the_server(self):
        superposed = self.client.solve(self.character.id, WEIGHTS[1])
        paper = self.client.solve(self.character.id, WEIGHTS[1], mix="rest-lengths")
        self.assertTrue(superposed.summaries[0].converged and paper.summaries[0].converged)
        # A two-target mix: the superposed prediction and the paper's blend of rest lengths are two answers.
        self.assertGreater(np.abs(superposed.positions - paper.positions).max(), 1e-4 * self.diagonal)
        # Every target a linear delta: the frame is its linear blend.
        names = list(self.targets)
        linear = self.client.solve(self.character.id, WEIGHTS[1], linear_targets=names)
        blend = self.client.solve(self.character.id, WEIGHTS[1], linear=True)
        np.testing.assert_allclose(linear.positions, blend.positions, atol=1e-5 * self.diagonal)
        # None named: the default's answer (the cylinder has no default corrective).
        none = self.client.solve(self.character.id, WEIGHTS[1], linear_targets=[])
        np.testing.assert_array_equal(none.positions, superposed.positions)
        for bad, named in (({"mix": "summed"}, "summed"), ({"linear_targets": ["no-such-target"]}, "no-such-target")):
            with self.assertRaises(springblend.SpringblendError) as caught:
                self.client.solve(self.character.id, WEIGHTS[1], **bad)
            self.assertEqual(caught.exception.code, grpc.StatusCode.INVALID_ARGUMENT)
            self.assertIn(named, caught.exception.message)

    def test_linear_option_is_the_linear_blend(self):
        solution = self.client.solve(self.character.id, [0.5, 0.25], linear=True)
        targets = list(self.targets.values())
        linear = self.rest + 0.5 * (targets[0] - self.rest) + 0.25 * (targets[1] - self.rest)
        np.testing.assert_allclose(solution.positions[0], linear, atol=1e-5 * self.diagonal)

    def test_interactive_session_answers_the_newest_frame(self):
        with self.client.interactive(self.character.id, colliders=[sphere(*BALL)]) as session:
            indices = [session.send(w) for w in WEIGHTS]
            session.close()
            frames = list(session)
        self.assertEqual(indices, [0, 1, 2])
        self.assertGreaterEqual(len(frames), 1)
        self.assertEqual(frames[-1].index, 2, "the last frame sent is never overtaken")
        self.assertTrue(frames[-1].summary.converged)
        alone = self.client.solve(self.character.id, WEIGHTS[2], colliders=[sphere(*BALL)])
        # Warm starts differ, so equal to the solver's tolerance rather than to the bit.
        self.assertLessEqual(np.abs(frames[-1].positions - alone.positions[0]).max(), 1e-4 * self.diagonal)

    def test_weights_by_name_are_the_positional_ones(self):
        names = list(self.targets)
        positional = self.client.solve(self.character.id, WEIGHTS[:2])
        named = self.client.solve(self.character.id, [dict(zip(names, w)) for w in WEIGHTS[:2]])
        np.testing.assert_array_equal(named.positions, positional.positions)
        one = self.client.solve(self.character.id, {names[1]: WEIGHTS[1][1]})  # the other target at 0
        np.testing.assert_array_equal(one.positions[0],
                                      self.client.solve(self.character.id, [0.0, WEIGHTS[1][1]]).positions[0])
        with self.client.interactive(self.character.id) as session:
            session.send({names[0]: 0.5})
            session.close()
            self.assertTrue(list(session)[-1].summary.converged)
        with self.assertRaises(springblend.SpringblendError) as caught:
            self.client.solve(self.character.id, [{names[0]: 0.5}, {"jawOpen": 1.0}])
        self.assertEqual(caught.exception.code, grpc.StatusCode.INVALID_ARGUMENT)
        self.assertIn(f"weights[1]: 'jawOpen' is not a target of this character (targets: {', '.join(names)})",
                      caught.exception.message)

    def test_characters_are_named_by_id_prefix_or_name(self):
        cid = self.character.id
        self.assertEqual(self.client.resolve(cid[:12]), cid)
        self.assertEqual(self.client.resolve("cylinder"), cid)
        self.assertEqual(self.client.get(cid[:20]).id, cid)
        np.testing.assert_array_equal(self.client.solve(cid[:12], WEIGHTS[0]).positions,
                                      self.client.solve(cid, WEIGHTS[0]).positions)
        with self.assertRaises(springblend.SpringblendError) as caught:
            self.client.get("0123")  # too short for a prefix, and no character has that name
        self.assertEqual(caught.exception.code, grpc.StatusCode.NOT_FOUND)
        self.assertIn("character '0123': no character on the server has this name", caught.exception.message)

    def test_wrong_weight_count_is_invalid_argument_with_the_servers_message(self):
        with self.assertRaises(springblend.SpringblendError) as caught:
            self.client.solve(self.character.id, [0.5, 0.5, 0.5])
        self.assertEqual(caught.exception.code, grpc.StatusCode.INVALID_ARGUMENT)
        self.assertIn("weight", caught.exception.message)
        self.assertIn("INVALID_ARGUMENT", str(caught.exception))

    def test_bad_collider_is_invalid_argument(self):
        with self.assertRaises(springblend.SpringblendError) as caught:
            self.client.solve(self.character.id, [0.5, 0.5], colliders=[box((0, 0, 0), (1, -1, 1))])
        self.assertEqual(caught.exception.code, grpc.StatusCode.INVALID_ARGUMENT)
        self.assertTrue(caught.exception.message)

    def test_unknown_character_is_not_found(self):
        unknown = "0" * 64
        for call in (lambda: self.client.get(unknown), lambda: self.client.solve(unknown, [0.5, 0.5])):
            with self.assertRaises(springblend.SpringblendError) as caught:
                call()
            self.assertEqual(caught.exception.code, grpc.StatusCode.NOT_FOUND)
            self.assertIn(unknown, caught.exception.message)

    def test_interactive_with_unknown_character_raises(self):
        with self.assertRaises(springblend.SpringblendError) as caught:
            with self.client.interactive("0" * 64) as session:
                session.send([0.5, 0.5])
                session.close()
                list(session)
        self.assertEqual(caught.exception.code, grpc.StatusCode.NOT_FOUND)

    def test_mismatched_target_is_refused_before_sending(self):
        with self.assertRaises(springblend.SpringblendError) as caught:
            self.client.upload(self.rest, self.faces, {"half": self.rest[:10]})
        self.assertEqual(caught.exception.code, grpc.StatusCode.INVALID_ARGUMENT)
        self.assertIn("half", caught.exception.message)

    def test_delete(self):
        rest, faces, targets = testing.cylinder()
        only_bend = {testing.CYLINDER_TARGETS[0]: targets[testing.CYLINDER_TARGETS[0]]}
        character = self.client.upload(rest, faces, only_bend, no_interior=True)
        self.client.delete(character.id)
        with self.assertRaises(springblend.SpringblendError) as caught:
            self.client.get(character.id)
        self.assertEqual(caught.exception.code, grpc.StatusCode.NOT_FOUND)


if __name__ == "__main__":
    unittest.main()
